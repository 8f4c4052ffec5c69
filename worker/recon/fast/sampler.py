"""Rays that can see the surface, and samples only where the surface can be.

Once per run, every zone of every view gets a fixed set of candidate directions spread evenly over its field of view;
each is marched through the hull (a signed-distance grid, negative inside) and kept only if it enters it, with the
segment [t_in, t_out] from its first entry to its last exit (padded). Each step then picks, for every histogram in the
batch, a stratified subset of its hull-hitting rays (weights rescaled so that the sum still estimates the integral
over the whole zone: rays that miss the hull see nothing) and places samples inside each ray's segment: a coarse pass
without gradients finds the first zero crossing of the current field, and the samples that carry gradients crowd
around it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from spadscan.protocol.errors import ConfigError


@dataclass
class HullRays:
    """Candidate rays that enter the hull, grouped by histogram (view * zones + zone), as torch tensors.

    origins (H, 3) and dirs (H, 3) world frame (metres, unit); t_in, t_out (H,) the padded hull segment (metres along
    the ray); weight (H,) steradians each candidate stands for; start, count (n_hist,) the slice of each histogram's
    rays; jitter_rad: angular spacing of the candidates (for per-step jitter).
    """

    origins: torch.Tensor
    dirs: torch.Tensor
    t_in: torch.Tensor
    t_out: torch.Tensor
    weight: torch.Tensor
    start: torch.Tensor
    count: torch.Tensor
    jitter_rad: float
    missed: "HullRays | None" = None
    """The candidates that miss the hull (same layout, t_in = t_out = 0), when asked for: they can still see a
    table."""

    @property
    def n_hist(self) -> int:
        return int(self.count.numel())


def _box_interval(o: torch.Tensor, d: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor):
    """Entry and exit distances (N,) of rays o + t d through the box [lo, hi]; t_exit < t_entry when missed."""
    inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    a, b = (lo - o) * inv, (hi - o) * inv
    t0 = torch.minimum(a, b).amax(dim=-1).clamp(min=0.0)
    t1 = torch.maximum(a, b).amin(dim=-1)
    return t0, t1


def hull_rays(inside: torch.Tensor, origin: torch.Tensor, voxel: float, poses: torch.Tensor,
              zone_dirs: torch.Tensor, zone_weights: torch.Tensor, *, pad_m: float, keep_missed: bool = False,
              chunk: int = 16384) -> HullRays:
    """March candidate rays through a boolean hull grid and keep those that enter it.

    inside: (nz, ny, nx) bool, nodes at origin + voxel * (x, y, z) where the surface may be; it is dilated by one
    node and marched at one-voxel steps with nearest-node lookups, which cannot step over a hull node.
    poses (V, 4, 4) sensor-to-world; zone_dirs (Z, D, 3) sensor-frame unit directions; zone_weights (Z, D) steradians.
    pad_m: segment padding on both ends (metres). Histogram h = v * Z + z. keep_missed: also return the candidates
    that miss the hull (`missed`).
    """
    V, Z, D = poses.shape[0], zone_dirs.shape[0], zone_dirs.shape[1]
    if zone_dirs.shape != (Z, D, 3) or zone_weights.shape != (Z, D) or inside.ndim != 3:
        raise ConfigError(f"zone directions {tuple(zone_dirs.shape)}, weights {tuple(zone_weights.shape)} and hull "
                          f"{tuple(inside.shape)} must be (Z, D, 3), (Z, D) and (nz, ny, nx)")
    dev, dt = poses.device, poses.dtype
    occ = torch.nn.functional.max_pool3d(inside.to(dev, torch.float32)[None, None], 3, 1, 1)[0, 0] > 0
    nz, ny, nx = occ.shape
    flat = occ.reshape(-1)
    origin = origin.to(dev, dt)
    n = torch.tensor([nx, ny, nz], device=dev, dtype=dt)
    lo, hi = origin, origin + (n - 1) * voxel
    dirs = torch.einsum("vij,zdj->vzdi", poses[:, :3, :3], zone_dirs).reshape(-1, 3)
    origins = poses[:, None, None, :3, 3].expand(V, Z, D, 3).reshape(-1, 3)
    weights = zone_weights[None].expand(V, Z, D).reshape(-1)
    t_in = torch.full((dirs.shape[0],), math.inf, device=dev, dtype=dt)
    t_out = torch.full_like(t_in, -math.inf)
    ramp = torch.arange(int(math.ceil(float((hi - lo).norm()) / voxel)) + 2, device=dev, dtype=dt) * voxel
    with torch.no_grad():
        for a in range(0, dirs.shape[0], chunk):
            o, d = origins[a: a + chunk], dirs[a: a + chunk]
            t0, t1 = _box_interval(o, d, lo, hi)
            t = t0[:, None] + ramp[None]  # (n, S)
            # The nearest node's flat index, one axis at a time: (n, S) arrays, not (n, S, 3) ones, whose short
            # last axis makes every element-wise pass several times slower.
            node = torch.zeros(t.shape, dtype=torch.long, device=dev)
            for axis, (size, stride) in enumerate(((nx, 1), (ny, nx), (nz, nx * ny))):
                i = torch.round((o[:, axis, None] + t * d[:, axis, None] - origin[axis]) / voxel).long()
                node += i.clamp_(0, size - 1) * stride
            hit_node = flat[node] & (t <= t1[:, None]) & (t1 > t0)[:, None]
            hit = hit_node.any(dim=1)
            first = torch.where(hit_node, t, torch.full_like(t, math.inf)).amin(dim=1)
            last = torch.where(hit_node, t, torch.full_like(t, -math.inf)).amax(dim=1)
            t_in[a: a + chunk] = torch.where(hit, (first - pad_m).clamp(min=1e-3), t_in[a: a + chunk])
            t_out[a: a + chunk] = torch.where(hit, last + pad_m, t_out[a: a + chunk])
    keep = torch.isfinite(t_in) & torch.isfinite(t_out) & (t_out > t_in)
    hist = torch.arange(V * Z, device=dev).repeat_interleave(D)
    jitter = float(torch.sqrt(zone_weights.sum(dim=1).mean() / D))

    def subset(mask, t0, t1):
        count = torch.bincount(hist[mask], minlength=V * Z)
        return HullRays(origins[mask], dirs[mask], t0[mask], t1[mask], weights[mask], torch.cumsum(count, 0) - count,
                        count, jitter)

    out = subset(keep, t_in, t_out)
    if keep_missed:
        zero = torch.zeros_like(t_in)
        out.missed = subset(~keep, zero, zero)
    return out


def pick_rays(rays: HullRays, hist_ids: torch.Tensor, per_hist: int, generator: torch.Generator | None):
    """A stratified subset of each histogram's hull-hitting rays, jittered by up to half the candidate spacing.

    hist_ids (n,) histograms with count > 0. Returns (ray_index (n * per_hist,), batch_hist (n * per_hist,) index into
    hist_ids, origins, dirs (n * per_hist, 3), weight (n * per_hist,) steradians: each candidate's weight times
    count / per_hist so that sums over the subset estimate sums over all candidates).
    """
    dev = rays.origins.device
    n = hist_ids.numel()
    count = rays.count[hist_ids].to(rays.t_in.dtype)
    u = (torch.arange(per_hist, device=dev, dtype=count.dtype)[None]
         + torch.rand(n, per_hist, device=dev, dtype=count.dtype, generator=generator)) / per_hist
    local = torch.minimum((u * count[:, None]).long(), rays.count[hist_ids][:, None] - 1)
    idx = (rays.start[hist_ids][:, None] + local).reshape(-1)
    batch = torch.arange(n, device=dev).repeat_interleave(per_hist)
    d = rays.dirs[idx]
    noise = torch.randn(d.shape, device=dev, dtype=d.dtype, generator=generator) * (0.5 * rays.jitter_rad)
    noise = noise - (noise * d).sum(-1, keepdim=True) * d
    d = torch.nn.functional.normalize(d + noise, dim=-1)
    w = rays.weight[idx] * (count[batch] / per_hist)
    return idx, batch, rays.origins[idx], d, w


def stratified(t_in: torch.Tensor, t_out: torch.Tensor, n: int, generator: torch.Generator | None) -> torch.Tensor:
    """n jittered, sorted samples per ray in [t_in, t_out]: (R,) x2 -> (R, n) metres."""
    R = t_in.numel()
    u = (torch.arange(n, device=t_in.device, dtype=t_in.dtype)[None]
         + torch.rand(R, n, device=t_in.device, dtype=t_in.dtype, generator=generator)) / n
    return t_in[:, None] + (t_out - t_in)[:, None] * u


def around_crossing(t_coarse: torch.Tensor, sdf_coarse: torch.Tensor, t_in: torch.Tensor, t_out: torch.Tensor,
                    n: int, half_width_m: float, generator: torch.Generator | None) -> torch.Tensor:
    """n sorted samples per ray in a window of +-half_width_m around the first zero crossing of the coarse field.

    t_coarse, sdf_coarse (R, S): coarse samples (sorted) and the field there. Rays without a crossing centre their
    window on the coarse sample with the smallest value (where a surface is most likely to grow). Windows are
    clipped to the hull segment. Returns (R, n) metres.
    """
    neg = sdf_coarse <= 0
    has = neg.any(dim=1)
    first_neg = torch.where(has, neg.float().argmax(dim=1), sdf_coarse.argmin(dim=1))
    prev = (first_neg - 1).clamp(min=0)
    t_a, t_b = t_coarse.gather(1, prev[:, None])[:, 0], t_coarse.gather(1, first_neg[:, None])[:, 0]
    f_a, f_b = sdf_coarse.gather(1, prev[:, None])[:, 0], sdf_coarse.gather(1, first_neg[:, None])[:, 0]
    frac = (f_a / (f_a - f_b).clamp(min=1e-9)).clamp(0.0, 1.0)
    centre = torch.where(has & (first_neg > 0), t_a + frac * (t_b - t_a), t_b)
    lo = torch.maximum(centre - half_width_m, t_in)
    hi = torch.minimum(lo + 2 * half_width_m, t_out)
    lo = torch.minimum(lo, hi)
    return stratified(lo, hi, n, generator)


__all__ = ["HullRays", "hull_rays", "pick_rays", "stratified", "around_crossing"]
