"""What the histograms say about each surface node: measured against expected photons at the rays' returns.

Each step, every rendered ray with an opaque return compares the measured photons of its histogram within
+-`window` bins of the return's bin with the model's (both less the background), and the log of the ratio goes to
the grid node nearest the return. Surface that the data holds reads a mean ratio near one; surface where the model
predicts photons that never came back (a lid the carving left over a cup's opening) reads well below one. The
erosion and the openings (parts/erosion.py, parts/openings.py) act on that evidence.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def return_ratios(expected: torch.Tensor, counts: torch.Tensor, background: torch.Tensor, valid: torch.Tensor,
                  window: int, min_sigma: float = 4.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Measured over expected signal photons around each bin, and where that ratio means something.

    expected, counts (H, B) photons (the model's expected counts and the measured ones); background (H,) photons per
    bin; valid (H, B) bool. Both signals are the counts less the background (negatives clipped), summed over the
    valid bins among b - window .. b + window (a bin the sensor does not record can neither confirm nor deny).
    Returns (ratio (H, B) = (measured + 1) / (expected + 1), significant (H, B): the expected signal stands
    `min_sigma` Poisson sigmas of the window's background above zero, so that a ratio below one is not noise).
    """
    if window < 0:
        raise ValueError(f"window {window} must be >= 0 bins")
    bg = background[:, None]
    model = (expected - bg).clamp(min=0.0) * valid
    meas = ((counts.to(expected.dtype) - bg) * valid).clamp(min=0.0)
    kernel = torch.ones(1, 1, 2 * window + 1, dtype=expected.dtype, device=expected.device)
    m = F.conv1d(model[:, None], kernel, padding=window)[:, 0]
    y = F.conv1d(meas[:, None], kernel, padding=window)[:, 0]
    significant = m > min_sigma * torch.sqrt(bg * (2 * window + 1) + 1.0)
    return (y + 1.0) / (m + 1.0), significant


class ReturnEvidence:
    """Per-node sums of the log ratio of measured to expected photons at the rays' returns (see the module)."""

    def __init__(self, shape: tuple[int, int, int], device):
        self.log_sum = torch.zeros(shape, device=device)
        self.hits = torch.zeros(shape, device=device)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.log_sum.shape)

    def add(self, points: torch.Tensor, log_ratio: torch.Tensor, origin: torch.Tensor, voxel: float) -> None:
        """Add log ratios (N,) at points (N, 3) (metres, world) to their nearest grid nodes; points off the grid drop
        out."""
        nz, ny, nx = self.shape
        idx = torch.round((points - origin) / voxel).long()
        size = torch.tensor([nx, ny, nz], device=idx.device)
        inside = ((idx >= 0) & (idx < size)).all(dim=1) & torch.isfinite(log_ratio)
        idx = idx[inside]
        flat = (idx[:, 2] * ny + idx[:, 1]) * nx + idx[:, 0]
        self.log_sum.view(-1).index_add_(0, flat, log_ratio[inside].to(self.log_sum.dtype))
        self.hits.view(-1).index_add_(0, flat, torch.ones_like(flat, dtype=self.hits.dtype))

    def take(self, min_hits: int, max_ratio: float) -> torch.Tensor:
        """Nodes (nz, ny, nx) bool with at least `min_hits` hits whose mean ratio is below `max_ratio`; then starts
        afresh."""
        out = self.classify(min_hits, max_ratio, math.inf)[0]
        self.log_sum.zero_()
        self.hits.zero_()
        return out

    def classify(self, min_hits: int, low: float, high: float) -> tuple[torch.Tensor, torch.Tensor]:
        """(flagged, supported): nodes (nz, ny, nx) bool with at least `min_hits` hits whose mean ratio is below
        `low`, and those whose mean ratio is at least `high`. Keeps the sums."""
        if not 0 < low <= high:
            raise ValueError(f"ratios {low} and {high} must satisfy 0 < low <= high")
        mean = self.log_sum / self.hits.clamp(min=1.0)
        enough = self.hits >= min_hits
        return enough & (mean < math.log(low)), enough & (mean >= math.log(high))


def step_returns(problem, step, window: int) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(points (m, 3) world metres, log ratio (m,)) of a step's opaque returns whose expected signal is significant
    (`return_ratios` within `window` bins), or None when the step recorded none. problem: the FastProblem; step: the
    StepRecord (its views, rates and hits). Computed once per step and window, however many parts read it."""
    if step.hits is None or step.hits[0].numel() == 0:
        return None
    key = ("returns", window)
    if key not in step.cache:
        step.cache[key] = _log_ratios(problem, step.views, step.rates, step.hits, window)
    return step.cache[key]


def _log_ratios(problem, views: torch.Tensor, rates: torch.Tensor, hits: tuple, window: int):
    fwd, n_bins = problem.forward, problem.counts.shape[-1]
    cycles = problem.cycles[views]
    expected = fwd.expected_counts(rates, cycles).reshape(-1, n_bins)
    bg = (problem.background[views] * cycles[:, None]).reshape(-1)
    ratio, significant = return_ratios(expected, problem.counts[views].reshape(-1, n_bins), bg,
                                       problem.valid[views].reshape(-1, n_bins), window)
    hist, points, ranges = hits
    b = torch.floor(fwd.sensor.bin_of_range(ranges)).long().clamp(0, n_bins - 1)
    keep = significant[hist, b]
    return points[keep], torch.log(ratio[hist, b][keep])


__all__ = ["return_ratios", "ReturnEvidence", "step_returns"]
