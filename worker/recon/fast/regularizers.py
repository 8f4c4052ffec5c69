"""Finite-difference regularisers on an SDF grid: Eikonal and smoothness, near the surface only.

Both act on the grid values directly (no autograd double-backward, no sampling): a step costs one pass over the
nodes. They are averaged over a band of nodes within `band_m` of the current surface, where the shape is decided;
far nodes are pinned by the hull constraint or carry no information.
"""

from __future__ import annotations

import torch


def _central(g: torch.Tensor, voxel: float):
    """Central differences on interior nodes: g (nz, ny, nx) -> (gx, gy, gz), each (nz-2, ny-2, nx-2), unitless."""
    gx = (g[1:-1, 1:-1, 2:] - g[1:-1, 1:-1, :-2]) / (2 * voxel)
    gy = (g[1:-1, 2:, 1:-1] - g[1:-1, :-2, 1:-1]) / (2 * voxel)
    gz = (g[2:, 1:-1, 1:-1] - g[:-2, 1:-1, 1:-1]) / (2 * voxel)
    return gx, gy, gz


def grid_regularizers(values: torch.Tensor, voxel: float, band_m: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Eikonal and smoothness terms of a grid (1, 1, nz, ny, nx) of SDF values (metres).

    eikonal = mean (|grad f| - 1)^2 over band nodes; smoothness = mean (voxel * laplacian f)^2 over band nodes, i.e.
    the squared change of the unit gradient across one voxel (dimensionless, ~ (voxel / radius of curvature)^2).
    Returns two scalars (zero when the band is empty).
    """
    g = values[0, 0]
    core = g[1:-1, 1:-1, 1:-1]
    band = (core.detach().abs() < band_m).to(g.dtype)
    n = band.sum().clamp(min=1.0)
    gx, gy, gz = _central(g, voxel)
    norm = torch.sqrt(gx * gx + gy * gy + gz * gz + 1e-12)
    eik = (((norm - 1.0) ** 2) * band).sum() / n
    lap = (g[1:-1, 1:-1, 2:] + g[1:-1, 1:-1, :-2] + g[1:-1, 2:, 1:-1] + g[1:-1, :-2, 1:-1]
           + g[2:, 1:-1, 1:-1] + g[:-2, 1:-1, 1:-1] - 6.0 * core) / voxel
    smooth = ((lap * lap) * band).sum() / n
    return eik, smooth


__all__ = ["grid_regularizers"]
