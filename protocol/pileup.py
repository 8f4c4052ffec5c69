"""First-photon (Coates) pile-up: from per-bin photon rates to detection probabilities, and back.

A SPAD that stops at its first photon in each laser cycle detects bin b with probability

    p_b = (1 - exp(-lambda_b)) * exp(-sum_{j<b} lambda_j),

and detects nothing in the cycle with probability exp(-sum_b lambda_b). Everything here works in float64 and in log
space (`expm1`, cumulative sums), so it stays finite for rates of zero and for rates far past saturation.
"""

from __future__ import annotations

import numpy as np

from .errors import SimulationError


def _check_rate(rate) -> np.ndarray:
    rate = np.asarray(rate, dtype=np.float64)
    if rate.ndim < 1 or rate.shape[-1] == 0:
        raise SimulationError(f"rates must have a bins axis, got shape {rate.shape}")
    if not np.all(np.isfinite(rate)) or np.any(rate < 0):
        raise SimulationError("rates must be finite and >= 0 photons per bin per cycle")
    return rate


def _rate_before(rate: np.ndarray) -> np.ndarray:
    """sum_{j<b} lambda_j for every b (exclusive cumulative sum along the last axis).

    Shifted, not `cumsum - rate`: subtracting a huge rate from a sum that holds it would cancel the smaller ones.
    """
    before = np.zeros_like(rate)
    with np.errstate(over="ignore"):  # sums past 1e308 become inf, and exp(-inf) = 0 is the right answer
        np.cumsum(rate[..., :-1], axis=-1, out=before[..., 1:])
    return before


def detection_probabilities(rate) -> np.ndarray:
    """Probability that a cycle's first detection falls in each bin.

    rate: (..., bins) photons per bin per cycle, >= 0. Returns (..., bins) float64 probabilities whose sum over bins
    is 1 - miss_probability(rate).
    """
    rate = _check_rate(rate)
    hit = -np.expm1(-rate)  # 1 - exp(-lambda), exact for small lambda, exactly 1 for huge lambda
    return hit * np.exp(-_rate_before(rate))


def miss_probability(rate) -> np.ndarray:
    """Probability that a cycle sees no photon in any bin: exp(-sum lambda). rate (..., bins) -> (...)."""
    rate = _check_rate(rate)
    with np.errstate(over="ignore"):
        return np.exp(-rate.sum(axis=-1))


def detection_probabilities_no_pileup(rate) -> np.ndarray:
    """Counts per cycle when every photon is counted (no dead time): the rate itself, (..., bins)."""
    return _check_rate(rate).copy()


def jitter_blur(prob, sigma_bins: float) -> np.ndarray:
    """Blur per-bin probabilities (..., bins) with a Gaussian of `sigma_bins` (timing jitter of the detector).

    Mass blurred past either end of the histogram is lost (it would be detected outside the recorded window).
    """
    prob = np.asarray(prob, dtype=np.float64)
    if not (np.isfinite(sigma_bins) and sigma_bins >= 0):
        raise SimulationError(f"jitter sigma {sigma_bins} bins must be finite and >= 0")
    if sigma_bins < 1e-3:
        return prob.copy()
    half = int(np.ceil(5 * sigma_bins))
    x = np.arange(-half, half + 1)
    k = np.exp(-0.5 * (x / sigma_bins) ** 2)
    k /= k.sum()
    n = prob.shape[-1]
    size = n + k.size - 1
    spec = np.fft.rfft(prob, size, axis=-1) * np.fft.rfft(k, size)
    out = np.fft.irfft(spec, size, axis=-1)[..., half: half + n]
    return np.maximum(out, 0.0)  # FFT round-off can dip below zero by ~1e-17


def coates_correct(counts, cycles) -> np.ndarray:
    """Coates' estimate of the photon rate per bin from first-photon counts.

    counts: (..., bins) detections over `cycles` laser cycles (scalar or broadcastable to counts[..., 0]).
    Returns (..., bins) float64 rates lambda_b = log(R_b) - log(R_b - c_b), where R_b = cycles - sum_{j<b} c_j are the
    cycles still live at bin b. Finite always: when a bin takes every remaining cycle (R_b - c_b = 0) half a cycle is
    assumed to survive (a lower bound on a rate the data cannot bound), and bins after all cycles are spent read 0
    (no information). Counts that exceed the stated cycles are treated as spending all of them.
    """
    c = np.asarray(counts, dtype=np.float64)
    if c.ndim < 1 or not np.all(np.isfinite(c)) or np.any(c < 0):
        raise SimulationError(f"counts must be finite and >= 0 with a bins axis, got shape {c.shape}")
    n = np.asarray(cycles, dtype=np.float64)
    if not np.all(np.isfinite(n)) or np.any(n <= 0):
        raise SimulationError(f"cycles must be finite and > 0, got {cycles}")
    n = n[..., None] if n.ndim else n
    live = np.maximum(n - _rate_before(c), 0.0)
    c = np.minimum(c, live)
    return np.log(np.maximum(live, 0.5)) - np.log(np.maximum(live - c, 0.5))


SHADOW = 0.02
"""A histogram is saturated when its detections per bin after its first return fall under this share of those
before it: the return stopped over 98 % of the cycles that reached it (about 4 photons a cycle, e^-4), so the
histogram holds only the leading edge of the nearest surface and nothing behind it. The simulated builtin sphere
at power 1 keeps 25 % or more after its returns, at power 100 none."""
SHADOW_GAP = 8
"""The bins either side of a histogram's highest bin left out of `saturated_histograms`' before and after (the
return itself): the histogram's length over this, at least one bin. 16 of the TMF8820's 128 bins, past its
pulse's long tail: with 2 (a 64th), the simulated TMF8820 sphere at 1000 times its power read 33 of its 144
histograms saturated, with 16, 73 (every one of LCSPCData's 1024-bin sphere at 100 times its power either way)."""
SHADOW_MIN_COUNTS = 20.0
"""Fewest detections the bins after a return would hold at the background's level before it, for its shadow to be
judged: SHADOW of that expects nothing, and none is a measurement (a capture without background has no shadow to
read, nor has a return in the histogram's last bins)."""
SATURATED_SHARE = 0.5
"""Share of a capture's histograms that must be saturated for it to be called saturated as a whole: taken at too much
flux (the near views of a tall object may saturate a few; of every histogram of LCSPCData's bunny and soap, its real
pyramid, the simulated lamp and the TMF8820 head on a can, none is)."""


def saturated_histograms(counts, valid=None) -> np.ndarray:
    """(...) bool: which first-photon histograms `counts` (..., bins) of measured detections (`valid` (..., bins)
    bool: the bins to read, default all) are saturated by pile-up: their detections per bin after their highest bin
    (SHADOW_GAP on) fall under SHADOW of the background's level before it (as far before; the median bin there, so
    that a weaker return in front, an object before a brighter table, is not taken for background). A first-photon
    sensor detects a bin's background only in the cycles still live there, so that ratio is the share of the cycles
    that the return left live (Coates): the cycles themselves need not be known. Judged only where the bins after
    would hold SHADOW_MIN_COUNTS detections at that level (a return in the first or last bins, or no background,
    says nothing here)."""
    c = np.asarray(counts, dtype=np.float64)
    if c.ndim < 1 or c.shape[-1] == 0 or not np.all(np.isfinite(c)) or np.any(c < 0):
        raise SimulationError(f"counts must be finite and >= 0 with a bins axis, got shape {c.shape}")
    valid = np.ones(c.shape, bool) if valid is None else np.broadcast_to(np.asarray(valid, bool), c.shape)
    c = np.where(valid, c, 0.0)
    n_bins = c.shape[-1]
    gap = max(1, n_bins // SHADOW_GAP)
    bins = np.arange(n_bins)
    peak = np.argmax(c, axis=-1)[..., None]
    before = valid & (bins < peak - gap)
    after = valid & (bins > peak + gap)
    n_after = after.sum(axis=-1)
    c_after = (c * after).sum(axis=-1)
    level = _median_where(c, before)
    shadow = c_after < SHADOW * level * n_after
    return (level * n_after >= SHADOW_MIN_COUNTS) & shadow


def saturated_count(counts, valid=None) -> tuple[int, int]:
    """(saturated, judged): of the histograms `counts` (..., bins) that hold a detection, how many are saturated
    (`saturated_histograms`, over the `valid` bins), and how many there are."""
    c = np.asarray(counts, dtype=np.float64)
    some = c.sum(axis=-1) > 0
    return int((saturated_histograms(c, valid) & some).sum()), int(some.sum())


def mostly_saturated(saturated: int, judged: int) -> bool:
    """Whether a capture is saturated as a whole: over SATURATED_SHARE of its `judged` histograms saturated."""
    return judged > 0 and saturated > SATURATED_SHARE * judged


def _median_where(values: np.ndarray, where: np.ndarray) -> np.ndarray:
    """The median of `values` (..., n) over the entries `where` (..., n) bool along the last axis; 0 where none."""
    count = where.sum(axis=-1)
    ranked = np.sort(np.where(where, values, np.inf), axis=-1)  # the chosen entries first, in order
    lo = np.take_along_axis(ranked, np.maximum((count - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(ranked, np.minimum(count // 2, values.shape[-1] - 1)[..., None], -1)[..., 0]
    return np.where(count > 0, 0.5 * (lo + hi), 0.0)
