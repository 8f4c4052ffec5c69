"""An explicit signed-distance grid read by trilinear interpolation, with coarse-to-fine refinement.

The grid covers an axis-aligned box with cubic voxels: node (i, j, k) sits at `origin + voxel * (i, j, k)` (x, y, z),
and the values are stored as a (1, 1, nz, ny, nx) tensor so that `grid_sample`'s (x, y, z) coordinate order maps onto
the box directly. Points outside the box read as empty: the value at the nearest point of the box (never below 0)
plus the distance to the box, so a field that is negative at a wall cannot leak a surface outside it.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage

from spadscan.protocol.errors import ConfigError


def grid_shape(bounds_min, bounds_max, resolution: int) -> tuple[tuple[int, int, int], float]:
    """Node counts (nx, ny, nz) and voxel size (metres) for a box whose longest side gets `resolution` nodes.

    The box is grown (at its max corner) to a whole number of voxels on the shorter sides.
    """
    lo, hi = np.asarray(bounds_min, float), np.asarray(bounds_max, float)
    ext = hi - lo
    if lo.shape != (3,) or not np.all(np.isfinite(ext)) or np.any(ext <= 0):
        raise ConfigError(f"grid box {lo.tolist()} .. {hi.tolist()} must be finite with max > min on every axis")
    if not (isinstance(resolution, (int, np.integer)) and 4 <= resolution <= 1024):
        raise ConfigError(f"grid resolution {resolution} must be an integer in [4, 1024]")
    voxel = float(ext.max()) / (resolution - 1)
    counts = tuple(int(max(2, math.ceil(e / voxel - 1e-6) + 1)) for e in ext)
    return counts, voxel


def signed_distance(occupancy: np.ndarray, voxel: float) -> np.ndarray:
    """Signed distance (metres, negative inside) of a boolean voxel grid (nz, ny, nx) -> float32 (nz, ny, nx).

    Each node's distance is to the nearest node of the other kind, less half a voxel, so the zero level lies halfway
    between an occupied and an empty node. An empty grid reads +inf-free: its distance is the grid's diagonal.
    """
    occ = np.asarray(occupancy, bool)
    if occ.ndim != 3:
        raise ConfigError(f"occupancy must be a 3-D grid (nz, ny, nx), got shape {occ.shape}")
    if not occ.any():
        return np.full(occ.shape, float(np.linalg.norm(occ.shape)) * voxel, np.float32)
    if occ.all():
        return np.full(occ.shape, -float(np.linalg.norm(occ.shape)) * voxel, np.float32)
    outside = ndimage.distance_transform_edt(~occ)  # distance to the nearest occupied node, for empty nodes
    inside = ndimage.distance_transform_edt(occ)  # distance to the nearest empty node, for occupied nodes
    d = np.where(occ, -(inside - 0.5), outside - 0.5) * voxel
    return d.astype(np.float32)


class GridField(torch.nn.Module):
    """SDF values on a regular grid (metres), differentiable by trilinear interpolation.

    origin: (3,) box min corner (metres); voxel: node spacing (metres); values: (nz, ny, nx) initial SDF.
    """

    def __init__(self, origin, voxel: float, values: torch.Tensor):
        super().__init__()
        if values.ndim != 3 or min(values.shape) < 2:
            raise ConfigError(f"grid values must be (nz, ny, nx) with >= 2 nodes per axis, got {tuple(values.shape)}")
        if not (math.isfinite(voxel) and voxel > 0):
            raise ConfigError(f"voxel size {voxel} m must be finite and > 0")
        self.voxel = float(voxel)
        self.register_buffer("origin", torch.as_tensor(np.asarray(origin, float), dtype=values.dtype,
                                                       device=values.device).reshape(3))
        self.sdf = torch.nn.Parameter(values.detach().clone()[None, None].contiguous())

    # ---- geometry of the box ----------------------------------------------------------------------------------
    @property
    def counts(self) -> tuple[int, int, int]:
        """Node counts (nx, ny, nz)."""
        nz, ny, nx = self.sdf.shape[2:]
        return nx, ny, nz

    @property
    def box_max(self) -> torch.Tensor:
        """Max corner of the box (3,), metres."""
        n = torch.tensor(self.counts, dtype=self.origin.dtype, device=self.origin.device)
        return self.origin + (n - 1) * self.voxel

    def node_points(self) -> torch.Tensor:
        """World positions of every node, (nz, ny, nx, 3) metres."""
        nx, ny, nz = self.counts
        dev, dt = self.origin.device, self.origin.dtype
        z, y, x = torch.meshgrid(torch.arange(nz, device=dev, dtype=dt), torch.arange(ny, device=dev, dtype=dt),
                                 torch.arange(nx, device=dev, dtype=dt), indexing="ij")
        return self.origin + self.voxel * torch.stack([x, y, z], dim=-1)

    # ---- reading ----------------------------------------------------------------------------------------------
    def _normalised(self, points: torch.Tensor) -> torch.Tensor:
        n = torch.tensor(self.counts, dtype=points.dtype, device=points.device)
        return torch.addcmul(torch.full_like(self.origin, -1.0) - self.origin * (2.0 / (self.voxel * (n - 1))),
                             points, 2.0 / (self.voxel * (n - 1)))

    def sample(self, points: torch.Tensor, values: torch.Tensor | None = None) -> torch.Tensor:
        """SDF at points (..., 3) metres -> (...). `values` (1, 1, nz, ny, nx) replaces the grid (e.g. constrained).

        Outside the box: max(value at the nearest box point, 0) + distance to the box (reads as empty).
        """
        grid = self.sdf if values is None else values
        shape = points.shape[:-1]
        p = points.reshape(-1, 3)
        lo, hi = self.origin, self.box_max
        inside_p = torch.minimum(torch.maximum(p, lo), hi)
        excess = (p - inside_p).norm(dim=-1)
        g = self._normalised(inside_p).reshape(1, -1, 1, 1, 3)
        v = F.grid_sample(grid, g, mode="bilinear", padding_mode="border", align_corners=True).reshape(-1)
        v = torch.where(excess > 0, torch.clamp(v, min=0.0) + excess, v)
        return v.reshape(shape)

    # ---- refinement -------------------------------------------------------------------------------------------
    def upsampled(self, factor: int = 2) -> "GridField":
        """A new field with `factor` x finer voxels over the same box; old nodes are kept, new ones interpolated.

        Trilinear interpolation restricted to each new cell is the old trilinear function, so the zero level set
        is unchanged. Node counts go from n to factor * (n - 1) + 1.
        """
        if not (isinstance(factor, int) and 1 <= factor <= 8):
            raise ConfigError(f"upsampling factor {factor} must be an integer in [1, 8]")
        nz, ny, nx = self.sdf.shape[2:]
        size = tuple(factor * (n - 1) + 1 for n in (nz, ny, nx))
        with torch.no_grad():
            fine = F.interpolate(self.sdf, size=size, mode="trilinear", align_corners=True)[0, 0]
        return GridField(self.origin.cpu().numpy(), self.voxel / factor, fine)


__all__ = ["GridField", "grid_shape", "signed_distance"]
