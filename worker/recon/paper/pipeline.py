"""From a field and views to rates: rays per zone in world space, samples along them, rendering, binning.

Shared by the presets; each preset decides where its samples go (the paper: stratified plus importance samples in
the scene sphere) and calls `render_transients` with them.
"""

from __future__ import annotations

import torch

from ..forward import TransientForward
from .render import Rendered, SDFField, Table, render_rays


def world_rays(poses: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of V views: poses (V, 4, 4) sensor-to-world, dirs (Z, R, 3) or (V, Z, R, 3) in the sensor frame.

    Returns (origins (V, Z, R, 3), directions (V, Z, R, 3)) in world metres."""
    rot, org = poses[:, :3, :3], poses[:, :3, 3]
    if dirs.ndim == 3:
        world = torch.einsum("vij,zrj->vzri", rot, dirs)
    else:
        world = torch.einsum("vij,vzrj->vzri", rot, dirs)
    return org[:, None, None, :].expand_as(world), world


def render_transients(field: SDFField, forward: TransientForward, origins: torch.Tensor, dirs: torch.Tensor,
                      ray_weight: torch.Tensor, t_samples: torch.Tensor, s, albedo, *, table: Table | None = None,
                      create_graph: bool = True) -> tuple[torch.Tensor, Rendered]:
    """Render H histograms' rays and bin them.

    origins, dirs: (H, R, 3); ray_weight: (H, R) solid angle per ray (sr; 0 drops a ray); t_samples: (H, R, S).
    Returns (transient (H, forward.n_fine), the Rendered samples of the H * R rays)."""
    h, r, n = t_samples.shape
    out = render_rays(field, origins.reshape(-1, 3), dirs.reshape(-1, 3), t_samples.reshape(-1, n), s, albedo,
                      table=table, create_graph=create_graph)
    p = out.ranges.shape[1]
    radiance = out.radiance * ray_weight.reshape(-1, 1)
    hist_id = torch.arange(h, device=t_samples.device).repeat_interleave(r * p)
    transient = forward.bin(out.ranges.reshape(-1), radiance.reshape(-1), hist_id, h)
    return transient, out
