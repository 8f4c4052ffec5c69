"""Finite-difference regularisers on an SDF grid: Eikonal and smoothness, on nodes near the surface.

Both act on the grid values directly (no autograd double-backward, no sampling of the field): central differences
and a 6-neighbour Laplacian at a random subset of the nodes within `band_m` of the surface, gathered by flat index,
so a step costs O(points) however fine the grid. The band is refreshed every few steps by the model.
"""

from __future__ import annotations

import torch


def band_nodes(values: torch.Tensor, band_m: float, bound: torch.Tensor | None = None) -> torch.Tensor:
    """Flat indices (n,) of interior nodes of a grid (1, 1, nz, ny, nx) whose |value| < band_m (metres).

    bound: the constraint's lower bound on the same grid; nodes held at it are left out (the projection decides
    them, and the kink where the bound takes over is no roughness of the surface)."""
    g = values.detach()[0, 0]
    keep = torch.zeros_like(g, dtype=torch.bool)
    keep[1:-1, 1:-1, 1:-1] = True
    keep &= g.abs() < band_m
    if bound is not None:
        keep &= g > bound[0, 0] + 1e-7
    return torch.nonzero(keep.reshape(-1))[:, 0]


def grid_regularizers(values: torch.Tensor, voxel: float, nodes: torch.Tensor, n_points: int,
                      generator: torch.Generator | None = None,
                      smooth_layers: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Eikonal and smoothness terms at up to n_points random nodes among `nodes` (flat interior indices).

    values: (1, 1, nz, ny, nx) SDF (metres). eikonal = mean (|grad f| - 1)^2 (central differences); smoothness =
    mean (voxel x laplacian f)^2, the squared change of the unit gradient across one voxel (dimensionless, ~ (voxel /
    radius of curvature)^2). smooth_layers: the smoothness counts only at nodes in the lowest this many z layers
    (the others add zero to its mean, so the weight per node stays the same); None: at every node. Returns two
    scalars (zero when there are no nodes).
    """
    if nodes.numel() == 0:
        zero = values.new_zeros(())
        return zero, zero
    if nodes.numel() > n_points:
        pick = torch.randint(0, nodes.numel(), (n_points,), device=nodes.device, generator=generator)
        nodes = nodes[pick]
    nz, ny, nx = values.shape[2:]
    step = torch.tensor([0, 1, -1, nx, -nx, nx * ny, -nx * ny], device=nodes.device)
    # One gather for the node and its six neighbours: its backward is one scatter into the grid, not seven.
    # index_select rather than advanced indexing: its backward is index_add_, half the time of the accumulating
    # index_put that indexing backs into on CPU.
    idx = (nodes[:, None] + step).reshape(-1)
    c, xp, xm, yp, ym, zp, zm = torch.index_select(values.reshape(-1), 0, idx).reshape(-1, 7).unbind(-1)
    grad = torch.stack([xp - xm, yp - ym, zp - zm], dim=-1) / (2 * voxel)
    norm = torch.sqrt((grad * grad).sum(-1) + 1e-12)
    eik = ((norm - 1.0) ** 2).mean()
    lap = (xp + xm + yp + ym + zp + zm - 6.0 * c) / voxel
    if smooth_layers is not None:
        lap = lap * (nodes < smooth_layers * nx * ny).to(lap.dtype)  # flat index = (z * ny + y) * nx + x
    return eik, (lap * lap).mean()


__all__ = ["band_nodes", "grid_regularizers"]
