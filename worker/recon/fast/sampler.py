"""Rays that can see the surface, and samples only where the surface can be.

Once per run, every zone of every view gets a fixed set of candidate directions spread evenly over its field of view;
each is marched through the hull (a signed-distance grid, negative inside) and kept only if it enters it, with the
segment [t_in, t_out] from its first entry to its last exit (padded). The march finds those two samples alone: from
each end of the ray it tests a few samples, then jumps ahead by the distance to the nearest hull node that no sample
in between can round to (`hull_rays`), so its cost is a few samples a ray, not the grid's diagonal (the candidates
of every view are marched, since training reads every view). Each step then picks, for every histogram in the
batch, a stratified subset of its hull-hitting rays (weights rescaled so that the sum still estimates the integral
over the whole zone: rays that miss the hull see nothing) and places samples inside each ray's segment: a coarse pass
without gradients finds the first zero crossing of the current field, and the samples that carry gradients crowd
around it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from scipy import ndimage

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


def _box_interval(o: torch.Tensor, d: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor):
    """Entry and exit distances (N,) of rays o + t d through the box [lo, hi]; t_exit < t_entry when missed."""
    inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    a, b = (lo - o) * inv, (hi - o) * inv
    t0 = torch.minimum(a, b).amax(dim=-1).clamp(min=0.0)
    t1 = torch.maximum(a, b).amin(dim=-1)
    return t0, t1


JUMP_SLACK = math.sqrt(3.0) + 0.01
"""Voxels taken off a jump along a ray (`_first_hit`): a sample rounds to a node at most half a voxel away on each
axis (sqrt(3)/2), both at the sample it jumps from and at one it could land short of, plus a margin for float32
rounding in the sample positions (a thousandth of a voxel at most on grids of a few hundred nodes)."""
MARCH_WINDOW = 4
"""Samples a ray tests at once before it jumps (`_first_hit`): near the hull most rays meet it within a few, and
each round costs one pass over the rays still marching (4 took 2.3 s for a 2000-view capture's 3.5 million rays,
2 took 2.8, 8 took 3.8)."""


def hull_rays(inside: torch.Tensor, origin: torch.Tensor, voxel: float, poses: torch.Tensor,
              zone_dirs: torch.Tensor, zone_weights: torch.Tensor, *, pad_m: float, keep_missed: bool = False,
              chunk: int = 1 << 18) -> HullRays:
    """March candidate rays through a boolean hull grid and keep those that enter it.

    inside: (nz, ny, nx) bool, nodes at origin + voxel * (x, y, z) where the surface may be; it is dilated by one
    node and marched at one-voxel steps with nearest-node lookups, which cannot step over a hull node.
    poses (V, 4, 4) sensor-to-world; zone_dirs (Z, D, 3) sensor-frame unit directions; zone_weights (Z, D) steradians.
    pad_m: segment padding on both ends (metres). Histogram h = v * Z + z. keep_missed: also return the candidates
    that miss the hull (`missed`).

    The samples lie at t0 + k voxels (t0: where the ray enters the grid's box, k = 0, 1, ...) and a sample is in the
    hull where its nearest node is. Only the first and the last such sample matter, and each is found from its end of
    the ray (`_first_hit`): the same samples as a march through every step gives, at a few samples a ray.
    """
    V, Z, D = poses.shape[0], zone_dirs.shape[0], zone_dirs.shape[1]
    if zone_dirs.shape != (Z, D, 3) or zone_weights.shape != (Z, D) or inside.ndim != 3:
        raise ConfigError(f"zone directions {tuple(zone_dirs.shape)}, weights {tuple(zone_weights.shape)} and hull "
                          f"{tuple(inside.shape)} must be (Z, D, 3), (Z, D) and (nz, ny, nx)")
    dev, dt = poses.device, poses.dtype
    occ = torch.nn.functional.max_pool3d(inside.to(dev, torch.float32)[None, None], 3, 1, 1)[0, 0] > 0
    nz, ny, nx = occ.shape
    origin = origin.to(dev, dt)
    n = torch.tensor([nx, ny, nz], device=dev, dtype=dt)
    lo, hi = origin, origin + (n - 1) * voxel
    dirs = torch.einsum("vij,zdj->vzdi", poses[:, :3, :3], zone_dirs).reshape(-1, 3)
    origins = poses[:, None, None, :3, 3].expand(V, Z, D, 3).reshape(-1, 3)
    weights = zone_weights[None].expand(V, Z, D).reshape(-1)
    t_in = torch.full((dirs.shape[0],), math.inf, device=dev, dtype=dt)
    t_out = torch.full_like(t_in, -math.inf)
    ramp = torch.arange(int(math.ceil(float((hi - lo).norm()) / voxel)) + 2, device=dev, dtype=dt) * voxel
    if bool(occ.any()):
        grid = _HullGrid(occ, origin, voxel, ramp)
        with torch.no_grad():
            for a in range(0, dirs.shape[0], chunk):
                first, last = grid.segments(origins[a: a + chunk], dirs[a: a + chunk])
                hit = torch.isfinite(first)
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


class _HullGrid:
    """A dilated hull grid marched along rays (`hull_rays`): its nodes, each node's distance to the nearest hull node,
    and the box of the hull's nodes."""

    def __init__(self, occ: torch.Tensor, origin: torch.Tensor, voxel: float, ramp: torch.Tensor):
        """occ (nz, ny, nx) bool, at least one node set; origin (3,) and voxel (metres); ramp (S,): k voxels."""
        self.dims = tuple(occ.shape[::-1])  # (nx, ny, nz)
        self.flat = occ.reshape(-1)
        clear = ndimage.distance_transform_edt(~occ.cpu().numpy())  # voxels, 0 on the hull
        self.clear = torch.as_tensor(clear, dtype=torch.float32, device=occ.device).reshape(-1)
        self.origin, self.voxel, self.ramp = origin, float(voxel), ramp
        nodes = occ.nonzero().flip(1).to(torch.float64)  # (x, y, z)
        # The hull's nodes' box, a voxel wider each side: no sample outside it rounds to one of them.
        self.box = (origin.double() + (nodes.amin(0) - 1) * voxel, origin.double() + (nodes.amax(0) + 1) * voxel)

    def segments(self, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(first, last) (n,) metres along rays o + t d (n, 3): the first and the last sample in the hull, inf and
        -inf where none is."""
        lo, hi = self.origin, self.origin + (torch.tensor(self.dims, dtype=o.dtype, device=o.device) - 1) * self.voxel
        t0, t1 = _box_interval(o, d, lo, hi)
        # Samples to test: those in the hull's box (a step more each way for rounding), none past the grid's box.
        e0, e1 = _box_interval(o.double(), d.double(), *self.box)
        top = self.ramp.numel() - 1
        k_lo = (torch.floor((e0 - t0.double()) / self.voxel) - 1).clamp(0, top).long()
        k_hi = (torch.ceil((torch.minimum(e1, t1.double()) - t0.double()) / self.voxel) + 1).clamp(-1, top).long()
        first = torch.full_like(t0, math.inf)
        last = torch.full_like(t0, -math.inf)
        rays = ((t1 > t0) & (e1 >= e0) & (k_hi >= k_lo)).nonzero().squeeze(1)
        k_first = self._first_hit(o[rays], d[rays], t0[rays], t1[rays], k_lo[rays], k_hi[rays], 1)
        hit = k_first >= 0
        rays, k_first = rays[hit], k_first[hit]
        k_last = self._first_hit(o[rays], d[rays], t0[rays], t1[rays], k_hi[rays], k_first, -1)
        first[rays] = t0[rays] + self.ramp[k_first]
        last[rays] = t0[rays] + self.ramp[k_last]
        return first, last

    def _first_hit(self, o, d, t0, t1, k, stop, step: int) -> torch.Tensor:
        """(n,) the first sample index from k towards stop (both included; step +1 forwards, -1 backwards) whose
        sample, at t0 + ramp[k] <= t1, lies in the hull; -1 where none does.

        Each round tests MARCH_WINDOW samples of every ray still marching; a ray with none in the hull jumps from its
        last one by that one's node's distance to the hull, less JUMP_SLACK: a sample rounds to a node within
        sqrt(3)/2 voxels of it, so a sample nearer than that distance cannot round to a hull node. Samples lie a voxel
        apart along a unit direction; a longer one (a pose whose rotation is not orthonormal) spaces them wider, and
        the jump is shortened by as much."""
        found = torch.full_like(k, -1)
        ids = torch.arange(k.numel(), device=k.device)
        stretch = d.norm(dim=1).clamp(min=1.0)
        top = self.ramp.numel() - 1
        ahead = torch.arange(MARCH_WINDOW, device=k.device) * step
        while ids.numel():
            kk = k[:, None] + ahead[None]
            t = t0[:, None] + self.ramp[kk.clamp(0, top)]
            within = ((kk <= stop[:, None]) if step > 0 else (kk >= stop[:, None])) & (t <= t1[:, None])
            node = self._nodes(o, d, t)
            hit = self.flat[node] & within
            got = hit.any(dim=1)
            found[ids[got]] = k[got] + step * hit[got].to(torch.uint8).argmax(dim=1)
            jump = torch.ceil((self.clear[node[:, -1]] - JUMP_SLACK) / stretch).clamp(min=1).long()
            k = k + step * (MARCH_WINDOW - 1 + jump)
            going = ~got & ((k <= stop) if step > 0 else (k >= stop))
            ids, o, d, t0, t1, k, stop, stretch = (x[going] for x in (ids, o, d, t0, t1, k, stop, stretch))
        return found

    def _nodes(self, o: torch.Tensor, d: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """(n, m) int32 flat index of the nearest node to each sample o + t d (t (n, m) metres), clamped to the grid.
        The arithmetic is the one fixed for these samples: the same floats give the same nodes in every run. One axis
        at a time: (n, m) arrays, not (n, m, 3) ones, whose short last axis makes every element-wise pass several
        times slower; int32 indices, whose passes take a third of int64's."""
        node = torch.zeros(t.shape, dtype=torch.int32, device=t.device)
        nx, ny, nz = self.dims
        for axis, (size, stride) in enumerate(((nx, 1), (ny, nx), (nz, nx * ny))):
            i = torch.round((o[:, axis, None] + t * d[:, axis, None] - self.origin[axis]) / self.voxel)
            node += i.to(torch.int32).clamp_(0, size - 1) * stride
        return node


def pick_rays(rays: HullRays, hist_ids: torch.Tensor, per_hist: int, generator: torch.Generator | None,
              jitter: bool = True):
    """A stratified subset of each histogram's hull-hitting rays, jittered by up to half the candidate spacing (unless
    not `jitter`).

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
    if jitter:
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
