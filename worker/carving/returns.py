"""Finding each histogram's first return: pile-up undone, background removed, a matched filter, a threshold.

The detection threshold is a z-score: a bin holds a return when the matched-filtered signal exceeds `threshold`
standard deviations of the filtered background noise. Steps, per histogram:

1. Coates' estimate turns first-photon counts into photons per bin (`N * lambda_b`), undoing pile-up, so that the
   background is flat again behind a strong return (sensors without pile-up skip this).
2. The background is estimated from runs of bins (see `background_rate`) and subtracted; on multi-zone sensors the
   crosstalk (a fixed share of all zones' signal in every zone) is unmixed. Histograms no sensor could have produced
   (`impossible_counts`, or those a caller marks unusable) are left out of that sum: unmixed with their counts, one
   corrupt zone would move every other zone of its view.
3. The signal is correlated with the pulse kernel (a matched filter). The correlation of the pulse with itself is
   symmetric about zero lag, so the filtered peak of one return sits at its arrival time: no offset for where the
   pulse's own peak lies after the arrival is needed.
4. The noise of each filtered bin follows from Poisson statistics of the background over the cycles still live at
   that bin (Coates' estimate grows noisier behind a strong return).

The *first* bin above the threshold is the return's onset: a surface whose return alone clears the threshold makes the
filtered signal clear it at or before the surface's arrival, so nothing lies in front of the onset (what space carving
relies on; its 'leading' filter keeps the onset close in front of the surface). The first clear peak in the run of
bins above the threshold that starts at the onset, refined to sub-bin by a parabola, is the arrival (what
reprojection relies on, with the 'leading' filter: see `detection_filter`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spadscan.protocol.errors import CaptureError
from spadscan.protocol.sensor_model import SensorModel

DEFAULT_THRESHOLD = 5.0
"""Default detection threshold (standard deviations of the matched-filtered background noise)."""
RESCAN = "scan again with more laser power, longer exposure or less ambient light, or from nearer"
"""What a capture too faint for carving's default level needs (said where a run finds one): thresholds set lower
only let photon noise pass for returns."""


def weak_level(threshold: float, weak_threshold: float | None) -> float:
    """The level carving keeps a weak return at (noise standard deviations): `weak_threshold` (None: the default
    threshold) capped at `threshold`. A histogram that clears it nowhere has its zone's whole field of view carved."""
    return min(threshold, DEFAULT_THRESHOLD if weak_threshold is None else weak_threshold)


def below_default_level(threshold: float, weak_threshold: float | None, default_threshold: float,
                        default_weak_threshold: float | None) -> bool:
    """Whether the thresholds in effect (noise standard deviations, as carving is given them) put carving's level
    (`weak_level`) below the level of the default ones. The level decides which histograms hold a return and which
    carve their zone's whole field of view, so only there does photon noise pass for returns the defaults refuse;
    the carving threshold lowered alone but above the level (4.5 over a weak threshold of 4) is not below it."""
    return weak_level(threshold, weak_threshold) < weak_level(default_threshold, default_weak_threshold)


@dataclass
class FirstReturns:
    """First return of every histogram. Arrays (n, zones); bin coordinates as in the sensor model (bin i covers
    [i, i + 1)), NaN where nothing was detected."""

    detected: np.ndarray
    """(n, zones) bool: some bin cleared the threshold."""
    onset_bin: np.ndarray
    """(n, zones) bin coordinate of the first bin above the threshold (its start: conservative)."""
    arrival_bin: np.ndarray
    """(n, zones) sub-bin arrival time of the first return (matched-filter peak)."""
    peak_z: np.ndarray
    """(n, zones) z-score of that peak (0 where nothing was detected)."""
    threshold: float

    def onset_range_m(self, sensor: SensorModel) -> np.ndarray:
        """(n, zones) one-way range (metres) in front of which every detected zone saw nothing; NaN if undetected."""
        return sensor.range_of_bin(self.onset_bin)

    def arrival_range_m(self, sensor: SensorModel) -> np.ndarray:
        """(n, zones) one-way range (metres) of the first return; NaN where nothing was detected."""
        return sensor.range_of_bin(self.arrival_bin)


def check_inputs(hists, poses, sensor: SensorModel) -> tuple[np.ndarray, np.ndarray]:
    """hists (n, zones, bins) counts >= 0 and poses (n, 4, 4) finite, matching the sensor; returns float64 copies."""
    h = np.asarray(hists)
    p = np.asarray(poses, dtype=np.float64)
    if h.ndim != 3 or h.shape[1:] != (sensor.n_zones, sensor.n_bins):
        raise CaptureError(f"histograms have shape {h.shape}, expected (n, {sensor.n_zones}, {sensor.n_bins})")
    if p.shape != (h.shape[0], 4, 4):
        raise CaptureError(f"poses have shape {p.shape}, expected ({h.shape[0]}, 4, 4)")
    h = h.astype(np.float64)
    if not (np.all(np.isfinite(h)) and np.all(h >= 0)):
        raise CaptureError("histogram counts must be finite and >= 0")
    if not np.all(np.isfinite(p)):
        raise CaptureError("poses must be finite")
    if h.shape[0] == 0:
        raise CaptureError("no histograms to work on")
    return h, p


def _live_cycles(counts: np.ndarray, cycles: float) -> np.ndarray:
    """Cycles still live at each bin (N minus detections in earlier bins), at least 1. (..., bins)."""
    before = np.zeros_like(counts)
    np.cumsum(counts[..., :-1], axis=-1, out=before[..., 1:])
    return np.maximum(cycles - before, 1.0)


def impossible_counts(hists: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """(n, zones) bool: histograms (n, zones, bins) that no histogram of `sensor.cycles` cycles could hold (the
    sensor's unreliable bins left out): on a first-photon (pile-up) sensor more counts than cycles, one detection a
    cycle at most; on any sensor every bin at the counter's limit. Such a histogram (a corrupt frame, a counter that
    overflowed) says nothing of its zone's signal. The test holds for views of summed frames too (`views`), whose
    cycles are the frames' sum, where a per-frame limit such as `plausibility`'s "over the counter" would not."""
    keep = np.ones(hists.shape[-1], bool)
    keep[list(sensor.ignore_bins)] = False
    if not keep.any():
        return np.zeros(hists.shape[:-1], bool)
    kept = hists[..., keep]
    bad = kept.min(axis=-1) >= sensor.max_count
    if sensor.pileup:
        # A view of fewer frames is scaled up to the others' cycles (`views`): a rounding error is no count.
        bad |= kept.sum(axis=-1) > sensor.cycles * (1 + 1e-9)
    return bad


def photon_signal(hists: np.ndarray, sensor: SensorModel,
                  usable: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Background-free photons per bin and the background's noise variance per bin.

    hists (n, zones, bins) counts. Returns (signal, variance), both (n, zones, bins) float64 in photons per bin over
    the histogram's cycles; bins the sensor marks unreliable carry zero signal. usable (n, zones) bool, or None for
    all: histograms marked False, and those `impossible_counts` finds, are left out of the crosstalk unmixing.
    """
    n_cyc = float(sensor.cycles)
    if sensor.pileup:
        live = _live_cycles(hists, n_cyc)
        c = np.minimum(hists, live - 0.5)  # a bin that took every live cycle: half a cycle survives (finite rate)
        rate = np.log(live) - np.log(live - c)
        photons = n_cyc * rate
    else:
        live = np.full_like(hists, n_cyc)
        photons = hists.copy()
    keep = np.ones(sensor.n_bins, bool)
    keep[list(sensor.ignore_bins)] = False
    bg = n_cyc * background_rate(np.where(keep, hists, 0.0), np.where(keep, live, 0.0))[..., None]
    signal = np.where(keep, photons - bg, 0.0)
    zones = signal.shape[-2]
    if sensor.crosstalk > 0 and zones > 1:
        signal = _unmix_crosstalk(signal, sensor.crosstalk, _crosstalk_sources(hists, sensor, usable))
    # Var of Coates' estimate of N * lambda for a background rate: N^2 * lambda / live = N * bg * (N / live).
    variance = np.maximum(bg, 1e-3) * (n_cyc / live)
    return signal, variance


def _crosstalk_sources(hists: np.ndarray, sensor: SensorModel, usable: np.ndarray | None) -> np.ndarray | None:
    """(n, zones) bool: the histograms whose signal enters the crosstalk sum, or None when all do."""
    good = ~impossible_counts(hists, sensor)
    if usable is not None:
        good &= np.broadcast_to(np.asarray(usable, bool), good.shape)
    return None if good.all() else good


def _unmix_crosstalk(signal: np.ndarray, c: float, sources: np.ndarray | None) -> np.ndarray:
    """Each zone's own signal from signals (n, zones, bins) that also hold `c` x the sum of all zones' signal.

    observed = (I + c 1 1^T) own, so own = observed - c / (1 + c Z) x (sum over zones of observed)
    (Sherman-Morrison); otherwise every zone would report the nearest return of any zone. `sources` (n, zones):
    the zones summed (None: all). A zone left out is taken to add no crosstalk (its own signal is unknown), so the
    sum runs over the Z' zones kept, with c / (1 + c Z').
    """
    if sources is None:
        return signal - c / (1 + c * signal.shape[-2]) * signal.sum(axis=-2, keepdims=True)
    kept = sources[..., None]
    total = np.where(kept, signal, 0.0).sum(axis=-2, keepdims=True)
    n_kept = kept.sum(axis=-2, keepdims=True)
    return signal - c / (1 + c * n_kept) * total


def background_rate(counts: np.ndarray, live: np.ndarray, blocks: int = 16) -> np.ndarray:
    """Flat background (photons per bin per cycle) of histograms (..., bins) given the live cycles per bin.

    The bins are cut into `blocks` runs; each run's rate is pooled (its counts over its live cycles, the maximum
    likelihood estimate of a flat rate) and the estimate is the median of the runs weighted by their live cycles. A
    return fills few runs, and runs far behind a strong return (few live cycles, little information) weigh little; a
    plain median of per-bin rates would read 0 there, where most bins hold no count at all.
    """
    n = counts.shape[-1]
    edges = np.linspace(0, n, min(blocks, n) + 1).astype(int)
    c = np.add.reduceat(counts, edges[:-1], axis=-1)
    w = np.add.reduceat(live, edges[:-1], axis=-1)
    p = np.clip(c / np.maximum(w, 1e-12), 0.0, 1 - 1e-12)
    rate = -np.log1p(-p)
    order = np.argsort(rate, axis=-1)
    r_sorted = np.take_along_axis(rate, order, -1)
    w_sorted = np.take_along_axis(w, order, -1)
    cum = np.cumsum(w_sorted, axis=-1)
    half = 0.5 * cum[..., -1:]
    idx = np.minimum(np.argmax(cum >= half, axis=-1), rate.shape[-1] - 1)
    return np.take_along_axis(r_sorted, idx[..., None], -1)[..., 0]


def _correlate(x: np.ndarray, kernel: np.ndarray, origin: int) -> np.ndarray:
    """out[..., i] = sum_k x[..., i + k - origin] * kernel[k] (zeros outside), by FFT along the last axis."""
    n, k = x.shape[-1], kernel.size
    size = 1 << int(np.ceil(np.log2(n + k)))
    spec = np.fft.rfft(x, size, axis=-1) * np.conj(np.fft.rfft(kernel, size))
    full = np.fft.irfft(spec, size, axis=-1)
    # irfft index j holds sum_k x[j + k] kernel[k]; we want shifts j = i - origin.
    idx = (np.arange(n) - origin) % size
    return full[..., idx]


FILTERS = ("matched", "leading")


def detection_filter(sensor: SensorModel, kind: str = "matched") -> tuple[np.ndarray, int, float]:
    """The filter correlated with the histograms: (kernel (K,), origin, lag in bins).

    'matched' is the pulse itself: the best signal-to-noise ratio, and its response to one return peaks at the
    arrival (lag 0), but the response is symmetric, so the pulse's slow tail shows up *before* the arrival too.
    'leading' is the pulse's rising half mirrored about its peak: a response with the pulse's sharp leading edge,
    peaking `lag` bins after the arrival (where the pulse peaks), a little less sensitive. Its first threshold
    crossing lies closer in front of a surface, which is what space carving wants, and reprojection too: where the
    pulse has a long tail (the TMF8820's, ~40 bins), the matched filter spreads a strong return's tail over the bins
    in front of it, bins of background alone then clear the threshold, and the first return's "peak" lands up to
    35 cm in front of the surface, behind the sensor even.
    """
    kernel, origin = sensor.pulse.kernel(1)
    kernel = kernel / kernel.max()
    if kind == "matched":
        return kernel, origin, 0.0
    if kind != "leading":
        raise CaptureError(f"detection filter {kind!r} is not one of {FILTERS}")
    mode = int(np.argmax(kernel))
    rise = kernel[: mode + 1]
    filt = np.concatenate([rise, rise[-2::-1]])
    # Where the filter's response to one pulse arriving at bin coordinate 0.5 (kernel[origin] in bin 0) peaks,
    # to sub-bin precision: that is the lag between an arrival and the response's peak.
    pulse = np.zeros(kernel.size + 2 * filt.size)
    pulse[filt.size: filt.size + kernel.size] = kernel
    resp = _correlate(pulse, filt, mode)
    i = int(np.argmax(resp))
    curv = resp[i - 1] - 2 * resp[i] + resp[i + 1]
    peak = i + (0.5 * (resp[i - 1] - resp[i + 1]) / curv if curv < 0 else 0.0)
    return filt, mode, float(peak - (filt.size + origin))


def matched_filter_z(hists, sensor: SensorModel, kind: str = "matched",
                     usable: np.ndarray | None = None) -> np.ndarray:
    """(n, zones, bins) z-scores of the filtered, background-free signal (see `detection_filter`; `usable`: see
    `photon_signal`).

    With the 'leading' filter, index i holds the response whose peak marks an arrival `lag` bins before bin i.
    """
    return _filtered_and_z(hists, sensor, kind, usable)[1]


def _filtered_and_z(hists, sensor: SensorModel, kind: str,
                    usable: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The filtered background-free signal (photons) and its z-scores, both (n, zones, bins), 0 at ignored bins."""
    signal, variance = photon_signal(np.asarray(hists, dtype=np.float64), sensor, usable)
    kernel, origin, _ = detection_filter(sensor, kind)
    filtered = _correlate(signal, kernel, origin)
    noise = np.sqrt(np.maximum(_correlate(variance, kernel ** 2, origin), 1e-12))
    z = filtered / noise
    z[..., list(sensor.ignore_bins)] = 0.0
    filtered[..., list(sensor.ignore_bins)] = 0.0
    return filtered, z


def first_returns(hists, sensor: SensorModel, threshold: float = DEFAULT_THRESHOLD,
                  filter: str = "matched", usable: np.ndarray | None = None) -> FirstReturns:
    """Onset and arrival of the first return in every histogram (n, zones, bins); see the module docstring.

    With the 'leading' filter the onset and arrival are moved back by the filter's lag (where the pulse peaks after
    the arrival), so both keep their meaning. usable (n, zones) bool, or None for all: histograms marked False
    detect nothing and are left out of the crosstalk unmixing (`photon_signal`).
    """
    if not (np.isfinite(threshold) and threshold > 0):
        raise CaptureError(f"detection threshold {threshold} must be > 0 (standard deviations of the noise)")
    lag = detection_filter(sensor, filter)[2]
    f, z = _filtered_and_z(hists, sensor, filter, usable)
    above = z > threshold
    if usable is not None:
        above &= np.asarray(usable, bool)[..., None]
    detected = above.any(axis=-1)
    onset = np.argmax(above, axis=-1)  # first bin above (0 where none: masked below)
    # The first return's peak: within the run of bins above the threshold that starts at the onset, the first local
    # maximum that reaches half the run's highest value (noise wiggles on a rising edge are not peaks). The z-scores
    # decide what is detected; the peak is the filtered signal's own: the noise rises behind a strong return (fewer
    # cycles left live), which would pull a peak of the z-scores towards the sensor by up to a bin.
    n_bins = z.shape[-1]
    bins = np.arange(n_bins)
    below = ~above & (bins >= onset[..., None])
    run_end = np.where(below.any(axis=-1), np.argmax(below, axis=-1), n_bins)
    in_run = (bins >= onset[..., None]) & (bins < run_end[..., None])
    run_max = np.where(in_run, f, -np.inf).max(axis=-1, keepdims=True)
    local_max = np.ones_like(above)
    local_max[..., :-1] = f[..., :-1] >= f[..., 1:]
    local_max[..., 1:] &= f[..., 1:] >= f[..., :-1]
    peak = np.argmax(in_run & local_max & (f >= 0.5 * run_max), axis=-1)
    zp = np.take_along_axis(z, peak[..., None], -1)[..., 0]
    fp = np.take_along_axis(f, peak[..., None], -1)[..., 0]
    fl = np.take_along_axis(f, np.maximum(peak - 1, 0)[..., None], -1)[..., 0]
    fr = np.take_along_axis(f, np.minimum(peak + 1, n_bins - 1)[..., None], -1)[..., 0]
    curv = fl - 2 * fp + fr
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(curv < 0, 0.5 * (fl - fr) / curv, 0.0)
    shift = np.clip(np.nan_to_num(shift), -0.5, 0.5)
    # Filter output index i corresponds to an arrival at the centre of bin i, coordinate i + 0.5.
    arrival = np.where(detected, peak + shift + 0.5 - lag, np.nan)
    onset_bin = np.where(detected, onset - lag, np.nan)
    return FirstReturns(detected, onset_bin, arrival, np.where(detected, zp, 0.0), float(threshold))
