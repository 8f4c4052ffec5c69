"""The laser pulse used by the forward model: the sensor model's, or one derived from reference histograms.

For the real TMF8820 the reference channel records the emitted pulse through an internal path. Fitted against the
zones (docs/sensor_models.md), the zones' pulse is the floor-subtracted reference, normalised to peak 1, shifted,
stretched by 1.10 in time and raised to the power 1.5: p(i) = ref_n(peak_ref + (i - (zero_bin - 0.59)) / 1.10) ** 1.5
for a return at zero range (i a bin index, peak_ref the reference's peak index, found per capture). The simulator
draws its reference from the inverse of this mapping, so that a simulated capture read as measured gives the sensor
model's pulse back.

That mapping still rises too slowly: a pulse fitted freely to the real pyramid's histograms (the geometry held) puts
0.8% of its area two bins before the peak, the mapped one 3.5%. So the kernel's bins before its peak are raised to
the power 2 relative to the peak (then renormalised). A pulse that starts too early lets the fit move near surfaces
away from the sensors; with the steeper edge the pyramid's data term falls 14% and its faces move out to the object
(benchmarks/RESULTS.md).
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
REF_RISE_POWER = 2.0
"""Power applied to the kernel's bins before its peak, relative to the peak (steepens the rising edge)."""
KERNEL_BEFORE, KERNEL_AFTER = 4, 24
"""Bins kept before and after the arrival in a reference-derived kernel (tail e-folding ~3.9 bins)."""


def pulse_kernel(sensor: SensorModel, reference: np.ndarray | None, oversample: int = 1):
    """(kernel (K,) summing to 1, origin, source) with kernel[origin + k] the response averaged over
    [k - 0.5, k + 0.5) / oversample bins after the arrival.

    reference: (B,) mean reference histogram of a measured capture, or None (then the sensor model's pulse). A
    reference without a clear peak above its floor falls back to the sensor model's pulse too."""
    if reference is not None:
        kernel = reference_kernel(reference, oversample)
        if kernel is not None:
            return kernel, KERNEL_BEFORE * oversample, "reference"
    kernel, origin = sensor.pulse.kernel(oversample)
    return kernel, int(origin), "sensor model"


def reference_kernel(ref: np.ndarray, oversample: int = 1, fine: int = 8) -> np.ndarray | None:
    """Pulse kernel ((KERNEL_BEFORE + KERNEL_AFTER + 1) * oversample,) from a mean reference histogram (B,), or None
    when it holds no peak clearly above its floor (5 sigma of Poisson noise)."""
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
    # x: offset after the arrival in bins (bin-centre coordinates); histogram index i = zero_bin + x - 0.5.
    n = (KERNEL_BEFORE + KERNEL_AFTER + 1) * oversample * fine
    x = (np.arange(n) + 0.5) / (oversample * fine) - KERNEL_BEFORE - 0.5 / oversample
    arg = peak + (x - 0.5 - REF_PEAK_SHIFT_BINS) / REF_STRETCH
    p = np.interp(arg, np.arange(ref.size), ref_n, left=0.0, right=0.0) ** REF_POWER
    k = p.reshape(-1, fine).mean(axis=1)
    if k.sum() <= 0:
        return None
    top = int(np.argmax(k))
    k[:top] = k[top] * (k[:top] / k[top]) ** REF_RISE_POWER
    return k / k.sum()
