"""The table under a real object: a plane rendered exactly, with its own albedo and (optionally) a fitted height.

Every zone of a real capture sees the table (SENSOR_FACTS: it is in every histogram), so its return is part of the
forward model, not noise to be explained by the object. Rays that enter the hull see it behind the object, dimmed
by the round-trip transmittance through the hull segment; rays that miss the hull see it directly — all of those are
rendered every step (cheap: one plane intersection each), so the table adds no sampling noise.

When the capture names no table height (a fitted table of a measured capture), `detect_height` finds a horizontal
one: the table is the farthest surface every zone sees, so at the right height the plane's predicted peak falls on
each zone's last significant peak and nothing is ever measured behind it; the best height starts the fit.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .sampler import HullRays

MIN_RANGE_M = 1e-3


class TableModel:
    """The plane normal . x = offset (normal unit, pointing to the free side), learned log albedo and, when
    `fit_offset`, a learned offset. Transients carry albedo / pi x cos / r^2 x sr, like the forward model's."""

    def __init__(self, normal, offset: float, albedo: float, fit_offset: bool, missed: HullRays, forward,
                 device):
        self.normal = torch.as_tensor(np.asarray(normal, float), dtype=torch.float32, device=device)
        self.offset = torch.tensor(float(offset), device=device, requires_grad=fit_offset)
        self.log_albedo = torch.tensor(math.log(albedo), device=device, requires_grad=True)
        self.fit_offset = fit_offset
        self.missed = missed
        self.forward = forward

    def parameters(self) -> list[torch.Tensor]:
        return [self.log_albedo] + ([self.offset] if self.fit_offset else [])

    def albedo_value(self) -> float:
        return float(torch.exp(self.log_albedo.detach()))

    def hit(self, o: torch.Tensor, d: torch.Tensor):
        """(range (R,), cos (R,), hit (R,) bool) of rays o, d (R, 3) meeting the plane from its free side."""
        nd = d @ self.normal
        t = (self.offset - o @ self.normal) / torch.where(nd < -1e-6, nd, -torch.ones_like(nd))
        hit = (nd < -1e-6) & (t > MIN_RANGE_M)
        return torch.where(hit, t, torch.ones_like(t)), (-nd).clamp(min=0.0), hit

    def returns(self, o: torch.Tensor, d: torch.Tensor, w: torch.Tensor, transmittance: torch.Tensor):
        """Table returns of rays o, d (R, 3) with weights w (R,) sr and round-trip transmittance (R,) in front of it:
        (ranges (R,) metres, values (R,))."""
        t, cos, hit = self.hit(o, d)
        value = transmittance * w * cos / (t * t) * (torch.exp(self.log_albedo) / math.pi)
        return t, torch.where(hit, value, torch.zeros_like(value))

    def open_transient(self, hist: torch.Tensor) -> torch.Tensor:
        """Transients (n, n_fine) of the rays of histograms `hist` (n,) that miss the hull (table only)."""
        m = self.missed
        cnt = m.count[hist]
        n = hist.numel()
        if int(cnt.sum()) == 0:
            return torch.zeros(n, self.forward.n_fine, device=hist.device)
        local = torch.arange(n, device=hist.device).repeat_interleave(cnt)
        first = torch.repeat_interleave(m.start[hist] - (torch.cumsum(cnt, 0) - cnt), cnt)
        idx = first + torch.arange(int(cnt.sum()), device=hist.device)
        t, v = self.returns(m.origins[idx], m.dirs[idx], m.weight[idx], torch.ones_like(m.weight[idx]))
        return self.forward.bin(t, v, local, n)

    def summary(self) -> dict:
        z = float(self.offset.detach()) / float(self.normal[2]) if abs(float(self.normal[2])) > 0.99 else None
        return {"table_albedo": self.albedo_value(), "table_offset_m": float(self.offset.detach()),
                "table_normal": self.normal.cpu().tolist(), "table_z_m": z, "table_fitted": self.fit_offset}


def last_peaks(counts: np.ndarray, cycles: np.ndarray, background: np.ndarray, ignore_bins=()) -> np.ndarray:
    """Bin of the last significant peak of every histogram (V, Z), or -1 where there is none.

    counts (V, Z, B); cycles (V,); background (V, Z) per bin per cycle. A peak is a local maximum of the 3-bin mean
    excess rate that stands 5 Poisson sigmas above the background and at 5% of the histogram's highest excess.
    """
    V, Z, B = counts.shape
    excess = counts / cycles[:, None, None] - background[..., None]
    if ignore_bins:
        excess[..., list(ignore_bins)] = 0.0
    sm = excess.copy()
    sm[..., 1:-1] = (excess[..., :-2] + excess[..., 1:-1] + excess[..., 2:]) / 3
    sd = np.sqrt(np.maximum(counts, 1.0)) / cycles[:, None, None] / math.sqrt(3)
    significant = (sm > 5 * sd) & (sm > 0.05 * sm.max(axis=-1, keepdims=True))
    local = np.zeros_like(significant)
    local[..., 1:-1] = (sm[..., 1:-1] >= sm[..., :-2]) & (sm[..., 1:-1] >= sm[..., 2:])
    return np.where(significant & local, np.arange(B), -1).max(axis=-1)


def plane_peak_bins(height: float, poses: np.ndarray, zone_dirs: np.ndarray, zone_weights: np.ndarray, sensor,
                    kernel: np.ndarray, origin: int) -> np.ndarray:
    """Bin (V, Z) where a horizontal plane at `height` alone would put each histogram's peak; -1 if out of view."""
    V, B = len(poses), sensor.n_bins
    dirs = np.einsum("vij,zdj->vzdi", poses[:, :3, :3], zone_dirs)
    down = dirs[..., 2] < -1e-3
    t = (height - poses[:, 2, 3][:, None, None]) / np.where(down, dirs[..., 2], -1.0)
    ok = down & (t > MIN_RANGE_M)
    b = np.floor(sensor.zero_bin + np.where(ok, t, 0.0) / sensor.bin_width_m).astype(int)
    good = ok & (b >= 0) & (b < B)
    raw = np.zeros((V, zone_dirs.shape[0], B))
    vi, zi, _ = np.nonzero(good)
    np.add.at(raw, (vi, zi, b[good]), (zone_weights[None] * -dirs[..., 2] / np.maximum(t, MIN_RANGE_M) ** 2)[good])
    lag = np.arange(B)[None, :] - np.arange(B)[:, None] + origin  # conv[b, i] = kernel[origin + i - b]
    conv = np.where((lag >= 0) & (lag < kernel.size), kernel[np.clip(lag, 0, kernel.size - 1)], 0.0)
    pred = raw @ conv
    return np.where(pred.max(axis=-1) > 0, pred.argmax(axis=-1), -1)


def detect_height(counts: np.ndarray, cycles: np.ndarray, background: np.ndarray, poses: np.ndarray,
                  zone_dirs: np.ndarray, zone_weights: np.ndarray, sensor, kernel: np.ndarray, origin: int,
                  *, depth_m: float = 0.6, step_m: float = 0.02, min_score: float = 0.1,
                  ignore_bins=()) -> float | None:
    """Height (metres) of a horizontal table below every sensor, or None when no height explains the data.

    The table is the farthest surface each zone sees: a plane at the right height puts its peak where the zone's
    last significant peak is, and nothing is ever measured behind it. The score of a height is the fraction of zones
    (that would see the plane) whose last peak lies within 1.5 bins of the plane's, less the fraction whose last peak
    lies more than 1.5 bins behind it. Heights from 2 cm below the lowest sensor down `depth_m` are tried every
    `step_m`, then every step_m / 10 around the best. counts (V, Z, B); cycles (V,); background (V, Z);
    poses (V, 4, 4); zone_dirs (Z, D, 3) and zone_weights (Z, D) in the sensor frame; kernel/origin: the pulse.
    """
    last = last_peaks(counts, cycles, background, ignore_bins)
    k = np.asarray(kernel, float)
    thin = max(1, zone_dirs.shape[1] // 48)  # ~48 rays per zone place a peak to a bin; more only cost time
    zone_dirs, zone_weights = zone_dirs[:, ::thin], zone_weights[:, ::thin]

    def score(h: float) -> float:
        pb = plane_peak_bins(h, poses, zone_dirs, zone_weights, sensor, k, origin)
        m = (pb >= 0) & (last >= 0)
        if not m.any():
            return -1.0
        return float((np.abs(pb - last)[m] <= 1.5).mean() - (last > pb + 1.5)[m].mean())

    top = float(poses[:, 2, 3].min()) - 0.02
    coarse = np.arange(top, top - depth_m, -step_m)
    h0 = float(coarse[int(np.argmax([score(h) for h in coarse]))])
    fine = np.arange(h0 + step_m, h0 - step_m, -step_m / 10)
    scores = [score(h) for h in fine]
    i = int(np.argmax(scores))
    return float(fine[i]) if scores[i] >= min_score else None


__all__ = ["TableModel", "detect_height", "last_peaks", "plane_peak_bins"]
