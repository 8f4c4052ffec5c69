"""The space-carving hull as the start and as a constraint of the fast reconstruction.

Carving keeps every voxel that no histogram proves empty, so the object lies inside the hull (up to the carving's
own errors on thin parts). The fast preset therefore (1) starts its SDF at the hull's signed distance and (2) never
lets the surface leave it: after every optimiser step the field is projected onto

    field >= max(hull_sdf - margin, floor_z - z)

i.e. the reconstructed solid stays inside the hull grown by `margin` and above the floor (the ground plane of a
simulated scene, the table top of a real one). The margin is what keeps thin parts safe: carving that shaves a thin
limb by less than the margin costs nothing.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage

from spadscan.protocol.errors import ConfigError

from .grid_field import GridField, signed_distance


class HullConstraint:
    """The lower bound max(hull_sdf - margin, floor_z - z) of the field, as a grid matching a GridField.

    hull: GridField holding the hull's signed distance (not trained); margin_m: how far the surface may grow past
    the hull (metres); floor_z: height below which nothing is solid (metres), or None.
    """

    def __init__(self, hull: GridField, margin_m: float, floor_z: float | None):
        if not (np.isfinite(margin_m) and 0 <= margin_m < 1.0):
            raise ConfigError(f"hull margin {margin_m} m must be in [0, 1)")
        self.hull = hull
        self.margin_m = float(margin_m)
        self.floor_z = None if floor_z is None else float(floor_z)
        self._bound: torch.Tensor | None = None
        self._shape: tuple | None = None

    def bound_at(self, points: torch.Tensor) -> torch.Tensor:
        """The lower bound at world points (..., 3) -> (...)."""
        with torch.no_grad():
            b = self.hull.sample(points) - self.margin_m
            if self.floor_z is not None:
                b = torch.maximum(b, self.floor_z - points[..., 2])
        return b

    def bound_for(self, field: GridField) -> torch.Tensor:
        """The lower bound on the field's nodes, (1, 1, nz, ny, nx), cached per grid shape."""
        key = (tuple(field.sdf.shape), float(field.voxel), field.sdf.device, field.sdf.dtype)
        if self._bound is None or self._shape != key:
            pts = field.node_points().to(self.hull.origin.dtype)
            self._bound = self.bound_at(pts).to(field.sdf.dtype)[None, None].contiguous()
            self._shape = key
        return self._bound

    def project(self, field: GridField) -> None:
        """Clamp the field in place to the bound (after every optimiser step)."""
        with torch.no_grad():
            field.sdf.copy_(torch.maximum(field.sdf, self.bound_for(field)))

    def start_field(self, origin, voxel: float, counts: tuple[int, int, int], device, dtype) -> GridField:
        """A field over the given grid whose surface is the bound's own surface (the grown hull above the floor)."""
        nx, ny, nz = counts
        probe = GridField(origin, voxel, torch.zeros((nz, ny, nx), device=device, dtype=dtype))
        return GridField(origin, voxel, self.bound_for(probe)[0, 0].clone())


def hull_field(occupancy: np.ndarray, origin, voxel: float, device, dtype=torch.float32) -> GridField:
    """A GridField of the hull's signed distance from a carved occupancy grid (nz, ny, nx) on the given lattice."""
    sd = signed_distance(occupancy, voxel)
    return GridField(origin, voxel, torch.as_tensor(sd, device=device, dtype=dtype))


def object_hull(occupancy: np.ndarray, origin, voxel: float, poses: np.ndarray, zone_dirs: np.ndarray,
                onset_m: np.ndarray, *, min_views: float = 0.2, depths_m=(0.0, 0.01, 0.02, 0.04)) -> np.ndarray:
    """The part of a carved occupancy (nz, ny, nx) that the histograms' first returns come from.

    Carving keeps whatever no view proved empty, which can include space that the views barely looked at (a skirt
    along the box's walls, specks beside the sensors). The object is where the first returns land: for every
    histogram with a return, points just beyond its onset range along its zone's directions (zone_dirs (Z, D, 3),
    sensor frame; onset_m (V, Z) metres, NaN where nothing was detected; poses (V, 4, 4)) vote for the connected
    piece of the hull they fall in. Pieces with fewer than `min_views` of the best piece's votes are dropped.
    Returns the cleaned copy.
    """
    occ = np.asarray(occupancy, bool)
    lab, n = ndimage.label(occ)
    if n <= 1:
        return occ.copy()
    V, Z = onset_m.shape
    ok = np.isfinite(onset_m)
    dirs = np.einsum("vij,zdj->vzdi", poses[:, :3, :3], zone_dirs[:, :: max(1, zone_dirs.shape[1] // 64)])
    shape = np.array(occ.shape[::-1])  # (nx, ny, nz)
    votes = np.zeros(n + 1, np.int64)
    for v in range(V):
        hit = np.zeros(n + 1, bool)
        for z in np.flatnonzero(ok[v]):
            for dep in depths_m:
                p = poses[v, :3, 3] + dirs[v, z] * (onset_m[v, z] + dep)
                i = np.round((p - np.asarray(origin, float)) / voxel).astype(np.int64)
                good = np.all((i >= 0) & (i < shape), axis=1)
                hit[lab[i[good, 2], i[good, 1], i[good, 0]]] = True
        hit[0] = False
        votes += hit
    keep = votes >= min_views * votes.max()
    keep[0] = False
    return keep[lab]


__all__ = ["HullConstraint", "hull_field", "object_hull"]
