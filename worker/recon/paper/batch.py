"""A batch of rays with their samples, rendered to histograms, with memory-bounded back-propagation.

The data loss depends on whole histograms, which sum over every ray of a view, so rays cannot simply be split into
independent mini-batches. When a batch holds more samples than `chunk_points`, `backprop_batch` renders it twice:
first every chunk without a graph to get the histograms and dLoss/dHistogram, then each chunk again with a graph,
back-propagating its share (the histogram gradient dotted with its contribution). The gradient is exact; peak memory
is one chunk's graph; the cost is one extra forward pass.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch

from ..forward import TransientForward
from .render import SDFField, Table, opacity, render_rays, round_trip_transmittance


@dataclass
class RayBatch:
    """Rays of nv views x Z zones x M rays per zone, in world metres.

    origins, dirs: (nv, Z, M, 3); t: (nv, Z, M, S) sorted sample ranges; coarse_sdf: (nv, Z, M, S0) the field at the
    first S0 (stratified) samples, no gradient; hit: (nv, Z, M) 1 where the ray crosses the scene sphere; returns:
    (nv, Z, M) 1 where it can return light: it crosses the scene sphere or meets the table (a ray that meets only
    the table sees it through empty space); weight: (nv, Z, M) solid angle carried by each ray (sr, 0 for rays
    that return nothing)."""

    views: torch.Tensor
    origins: torch.Tensor
    dirs: torch.Tensor
    t: torch.Tensor
    coarse_sdf: torch.Tensor
    hit: torch.Tensor
    returns: torch.Tensor
    weight: torch.Tensor | None = field(default=None)

    @property
    def n_hist(self) -> int:
        return int(self.origins.shape[0] * self.origins.shape[1])

    @property
    def n_rays(self) -> int:
        return int(self.origins.shape[:3].numel())

    @property
    def n_samples(self) -> int:
        return int(self.t.numel())

    def concat(self, other: "RayBatch") -> "RayBatch":
        """Rays of both batches (same views), zone by zone: M = M1 + M2."""
        cat = lambda a, b: None if a is None else torch.cat([a, b], dim=2)  # noqa: E731
        return RayBatch(self.views, cat(self.origins, other.origins), cat(self.dirs, other.dirs),
                        cat(self.t, other.t), cat(self.coarse_sdf, other.coarse_sdf), cat(self.hit, other.hit),
                        cat(self.returns, other.returns),
                        None if self.weight is None or other.weight is None else cat(self.weight, other.weight))

    def coarse_contribution(self, s: float) -> torch.Tensor:
        """(nv, Z, M) each ray's coarse return, sum alpha T / t^2 (no shading), from the stored coarse SDF."""
        with torch.no_grad():
            t = self.t[..., : self.coarse_sdf.shape[-1]]
            alpha = opacity(self.coarse_sdf, s)
            w = alpha * round_trip_transmittance(alpha)[..., :-1]
            mid = 0.5 * (t[..., 1:] + t[..., :-1])
            return (w / mid.clamp_min(1e-4) ** 2).sum(-1) * self.hit


def _chunks(batch: RayBatch, chunk_points: int):
    """(ray slice start, stop) over the flattened rays so that each chunk holds about chunk_points samples."""
    n_rays, per_ray = batch.n_rays, batch.t.shape[-1]
    step = max(1, chunk_points // max(per_ray, 1))
    return [(i, min(i + step, n_rays)) for i in range(0, n_rays, step)]


def _render_chunk(field_, forward, batch, start, stop, s, albedo, table, create_graph):
    """(transient (H, n_fine), sample gradients (k, S, 3)) of rays [start, stop) of the flattened batch."""
    m, n = batch.origins.shape[2], batch.t.shape[-1]
    o = batch.origins.reshape(-1, 3)[start:stop]
    d = batch.dirs.reshape(-1, 3)[start:stop]
    t = batch.t.reshape(-1, n)[start:stop]
    w = batch.weight.reshape(-1)[start:stop]
    out = render_rays(field_, o, d, t, s, albedo, table=table, create_graph=create_graph)
    p = out.ranges.shape[1]
    hist = (torch.arange(start, stop, device=o.device) // m).repeat_interleave(p)
    transient = forward.bin(out.ranges.reshape(-1), (out.radiance * w[:, None]).reshape(-1), hist, batch.n_hist)
    return transient, out.grad


def batch_transient(field_: SDFField, forward: TransientForward, batch: RayBatch, s, albedo, table: Table | None,
                    chunk_points: int) -> torch.Tensor:
    """Transients (nv * Z, n_fine) of a batch, without a graph (normals still come from the field's gradient)."""
    total = None
    for start, stop in _chunks(batch, chunk_points):
        tr, _ = _render_chunk(field_, forward, batch, start, stop, s, albedo, table, False)
        tr = tr.detach()
        total = tr if total is None else total + tr
    return total


def backprop_batch(field_: SDFField, forward: TransientForward, batch: RayBatch, s, albedo, table: Table | None,
                   data_loss: Callable[[torch.Tensor], torch.Tensor], eikonal_weight: float,
                   chunk_points: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Back-propagate data_loss(transient (nv * Z, n_fine)) + eikonal_weight x mean (|grad f| - 1)^2 over the
    batch's samples into every parameter. Returns the (detached) data loss and Eikonal mean."""
    chunks = _chunks(batch, chunk_points)
    if len(chunks) == 1:
        tr, grad = _render_chunk(field_, forward, batch, 0, batch.n_rays, s, albedo, table, True)
        data = data_loss(tr)
        eik = ((grad.norm(dim=-1) - 1.0) ** 2).mean()
        (data + eikonal_weight * eik).backward()
        return data.detach(), eik.detach()
    with torch.no_grad():
        s_d = s.detach() if torch.is_tensor(s) else s
        a_d = albedo.detach() if torch.is_tensor(albedo) else albedo
        t_d = None if table is None else Table(table.normal, table.offset.detach(), table.albedo.detach())
    total = batch_transient(field_, forward, batch, s_d, a_d, t_d, chunk_points).requires_grad_(True)
    with torch.enable_grad():
        data = data_loss(total)
        (g_hist,) = torch.autograd.grad(data, total)
    n_total = batch.n_samples
    eik_sum = torch.zeros((), dtype=total.dtype, device=total.device)
    for start, stop in chunks:
        tr, grad = _render_chunk(field_, forward, batch, start, stop, s, albedo, table, True)
        eik = ((grad.norm(dim=-1) - 1.0) ** 2).sum()
        # The small graph of s, albedo and the table is shared by every chunk: keep it for the next one.
        ((tr * g_hist).sum() + eikonal_weight * eik / n_total).backward(retain_graph=True)
        eik_sum = eik_sum + eik.detach()
    return data.detach(), eik_sum / n_total
