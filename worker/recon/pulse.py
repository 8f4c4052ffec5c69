"""The laser pulse used by the forward model: the sensor model's, or one derived from reference histograms.

For the TMF8820 the reference channel records the emitted pulse through an internal path. Fitted against the zones
(SENSOR_FACTS), the zones' pulse is the floor-subtracted reference, normalised to peak 1, shifted, stretched by 1.10
in time and raised to the power 1.5: p(i) = ref_n(peak_ref + (i - (zero_bin - 0.59)) / 1.10) ** 1.5 for a return at
zero range (i a bin index, peak_ref the reference's peak index, found here per capture).
"""

from __future__ import annotations

import numpy as np

from spadscan.protocol.sensor_model import SensorModel

REF_STRETCH = 1.10
"""Time stretch from the reference pulse to the zones' pulse."""
REF_POWER = 1.5
"""Power applied to the normalised reference (narrows its over-wide tail)."""
REF_PEAK_SHIFT_BINS = -0.59
"""Pulse peak index minus the zero-range bin coordinate (12.66 - 13.25 in the fit)."""
KERNEL_BEFORE, KERNEL_AFTER = 4, 24
"""Bins kept before and after the arrival in a reference-derived kernel (tail e-folding ~3.9 bins)."""


def pulse_kernel(sensor: SensorModel, reference: np.ndarray | None) -> tuple[np.ndarray, int, str]:
    """(kernel (K,) summing to 1, origin index of the arrival, source) for a capture.

    reference: (N, B) reference histograms of the capture's frames, or None. The reference is used when the sensor
    model says it carries one and it holds a clear peak; otherwise the sensor model's pulse.
    """
    if reference is not None and sensor.has_reference:
        kernel = reference_kernel(np.asarray(reference, np.float64).mean(axis=0))
        if kernel is not None:
            return kernel, KERNEL_BEFORE, "reference"
    kernel, origin = sensor.pulse.kernel(1)
    return kernel, int(origin), "sensor model"


def reference_kernel(ref: np.ndarray, oversample: int = 8) -> np.ndarray | None:
    """Pulse kernel from a mean reference histogram (B,), or None when it holds no peak above its floor.

    Returns (KERNEL_BEFORE + KERNEL_AFTER + 1,) values, entry KERNEL_BEFORE + k being the pulse averaged over
    [k - 0.5, k + 0.5) bins after the arrival.
    """
    ref = np.asarray(ref, np.float64)
    if ref.ndim != 1 or ref.size < 8 or not np.all(np.isfinite(ref)):
        return None
    floor = float(np.percentile(ref, 25))
    signal = np.clip(ref - floor, 0.0, None)
    peak_i = int(np.argmax(signal))
    if signal[peak_i] <= 0 or signal[peak_i] < 5 * np.sqrt(max(floor, 1.0)):
        return None
    ref_n = signal / signal[peak_i]
    peak = float(peak_i)
    if 0 < peak_i < ref.size - 1:  # parabolic refinement of the peak position
        a, b, c = ref_n[peak_i - 1], ref_n[peak_i], ref_n[peak_i + 1]
        denom = a - 2 * b + c
        if denom < 0:
            peak += float(np.clip(0.5 * (a - c) / denom, -0.5, 0.5))
    # Offset x (bins after the arrival, bin-centre coordinates) <-> histogram index i = zero_bin + x - 0.5.
    x = (np.arange((KERNEL_BEFORE + KERNEL_AFTER + 1) * oversample) + 0.5) / oversample - KERNEL_BEFORE - 0.5
    arg = peak + (x - 0.5 - REF_PEAK_SHIFT_BINS) / REF_STRETCH
    p = np.interp(arg, np.arange(ref.size), ref_n, left=0.0, right=0.0) ** REF_POWER
    k = p.reshape(-1, oversample).mean(axis=1)
    if k.sum() <= 0:
        return None
    return k / k.sum()
