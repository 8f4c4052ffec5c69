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
