"""Where to sample along rays: the ray's segment inside the scene sphere, stratified samples, and importance samples
drawn from the coarse opacity (NeuS-style up-sampling, without gradient)."""

from __future__ import annotations

import torch

from .render import opacity, round_trip_transmittance


def sphere_interval(origins: torch.Tensor, dirs: torch.Tensor, center: torch.Tensor, radius: float,
                    near_min: float, far_max: torch.Tensor | None = None):
    """Segment of each ray inside the sphere: (near (R,), far (R,), hit (R,) bool).

    origins, dirs (R, 3) (dirs unit); near is at least `near_min` metres; far at most `far_max` (R,) (e.g. the table
    hit). Rays that miss get near = far = near_min and hit False."""
    oc = origins - center
    b = (oc * dirs).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - radius * radius)
    root = torch.sqrt(disc.clamp_min(0.0))
    near = (-b - root).clamp_min(near_min)
    far = -b + root
    if far_max is not None:
        far = torch.minimum(far, far_max)
    hit = (disc > 0) & (far > near + 1e-9)
    near = torch.where(hit, near, torch.full_like(near, near_min))
    far = torch.where(hit, far, near)
    return near, far, hit


def stratified(near: torch.Tensor, far: torch.Tensor, n: int, *, jitter: bool,
               generator: torch.Generator | None = None) -> torch.Tensor:
    """n sorted ranges (R, n) per ray between near (R,) and far (R,), one in each of n equal strata (its centre when
    jitter is False, else uniform inside it); both ends included as stratum edges."""
    edges = torch.arange(n, dtype=near.dtype, device=near.device)
    if jitter:
        u = torch.rand(near.shape + (n,), generator=generator, dtype=torch.float64).to(near)
    else:
        u = torch.full(near.shape + (n,), 0.5, dtype=near.dtype, device=near.device)
    frac = (edges + u) / n
    return near[:, None] + (far - near)[:, None] * frac


def importance(t: torch.Tensor, sdf: torch.Tensor, s: float, n: int, *, jitter: bool,
               generator: torch.Generator | None = None) -> torch.Tensor:
    """n more ranges (R, n) per ray drawn by inverse CDF from the rendering weights alpha T of the coarse samples
    t (R, S) with SDF values sdf (R, S) at sharpness s (1/metres). No gradient. Rays with no weight sample evenly."""
    with torch.no_grad():
        alpha = opacity(sdf, s)
        w = alpha * round_trip_transmittance(alpha)[:, :-1]
        w = w + 1e-5 * w.sum(-1, keepdim=True).clamp_min(1e-12) + 1e-12  # keep every interval reachable
        cdf = torch.cumsum(w, -1)
        cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf / cdf[:, -1:]], -1)  # (R, S)
        if jitter:
            u = torch.rand(t.shape[0], n, generator=generator, dtype=torch.float64).to(t)
            u = (torch.arange(n, dtype=t.dtype, device=t.device) + u) / n
        else:
            u = ((torch.arange(n, dtype=t.dtype, device=t.device) + 0.5) / n).expand(t.shape[0], n)
        idx = torch.searchsorted(cdf.contiguous(), u.contiguous(), right=True).clamp(1, t.shape[1] - 1)
        c0, c1 = cdf.gather(1, idx - 1), cdf.gather(1, idx)
        t0, t1 = t.gather(1, idx - 1), t.gather(1, idx)
        frac = ((u - c0) / (c1 - c0).clamp_min(1e-12)).clamp(0.0, 1.0)
        return t0 + frac * (t1 - t0)


def merge(t: torch.Tensor, extra: torch.Tensor) -> torch.Tensor:
    """Sorted union of two sets of ranges (R, S) and (R, n) -> (R, S + n)."""
    return torch.sort(torch.cat([t, extra], -1), -1).values
