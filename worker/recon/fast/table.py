"""The table under a real object: a plane rendered exactly, with its own albedo and (optionally) a fitted height.

Every zone of a real capture sees the table (SENSOR_FACTS: it is in every histogram), so its return is part of the
forward model, not noise to be explained by the object. Rays that enter the hull see it behind the object, dimmed
by the round-trip transmittance through the hull segment; rays that miss the hull see it directly — all of those are
rendered every step (cheap: one plane intersection each), so the table adds no sampling noise.

When the capture names no table, `detect_height` finds a horizontal one: for each candidate height it renders the
plane alone and scores how well the predicted returns line up with the measured ones (a matched filter summed over
every histogram); the best height, if it explains the data clearly, starts the fit.
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


def detect_height(counts: np.ndarray, cycles: np.ndarray, background: np.ndarray, poses: np.ndarray,
                  zone_dirs: np.ndarray, zone_weights: np.ndarray, sensor, kernel: np.ndarray, origin: int,
                  *, depth_m: float = 0.6, step_m: float = 0.002, min_score: float = 0.3) -> float | None:
    """Height (metres) of a horizontal table seen from below every sensor, or None.

    counts (V, Z, B); cycles (V,); background (V, Z) per bin per cycle; poses (V, 4, 4); zone_dirs (Z, D, 3) and
    zone_weights (Z, D) sensor-frame rays; kernel/origin: the pulse per bin. Candidates run from just below the
    lowest sensor to `depth_m` below it. The score of a height is the correlation, over all histograms and bins,
    between the measured excess rate and the rendered table-only rate; None when the best is below `min_score`.
    """
    V, Z, B = counts.shape
    excess = counts / cycles[:, None, None] - background[..., None]
    excess = np.clip(excess, 0.0, None).reshape(V * Z, B)
    e_norm = math.sqrt(float((excess * excess).sum())) + 1e-30
    dirs = np.einsum("vij,zdj->vzdi", poses[:, :3, :3], zone_dirs).reshape(V * Z, -1, 3)
    oz = np.repeat(poses[:, 2, 3], Z)[:, None]
    w = np.broadcast_to(zone_weights[None], (V, Z, zone_weights.shape[1])).reshape(V * Z, -1)
    down = dirs[..., 2] < -1e-3
    k = np.asarray(kernel, float)
    # conv[b, i]: response in bin i to an arrival in bin b (kernel[origin + i - b]).
    lag = np.arange(B)[None, :] - np.arange(B)[:, None] + origin
    conv = np.where((lag >= 0) & (lag < k.size), k[np.clip(lag, 0, k.size - 1)], 0.0)
    rows = np.broadcast_to(np.arange(V * Z)[:, None], down.shape)

    def score(h: float) -> float:
        t = (h - oz) / np.where(down, dirs[..., 2], -1.0)
        ok = down & (t > MIN_RANGE_M)
        b = np.floor(sensor.zero_bin + np.where(ok, t, 0.0) / sensor.bin_width_m).astype(int)
        good = ok & (b >= 0) & (b < B)
        raw = np.zeros((V * Z, B))
        np.add.at(raw, (rows[good], b[good]), (w * -dirs[..., 2] / np.maximum(t, MIN_RANGE_M) ** 2)[good])
        pred = raw @ conv
        return float((pred * excess).sum()) / (math.sqrt(float((pred * pred).sum())) * e_norm + 1e-30)

    top = float(poses[:, 2, 3].min()) - 0.02
    coarse = np.arange(top, top - depth_m, -4 * step_m)
    scores = [score(h) for h in coarse]
    h0 = float(coarse[int(np.argmax(scores))])
    fine = np.arange(h0 + 4 * step_m, h0 - 4 * step_m, -step_m / 2)
    fs = [score(h) for h in fine]
    i = int(np.argmax(fs))
    return float(fine[i]) if fs[i] >= min_score else None


__all__ = ["TableModel", "detect_height"]
