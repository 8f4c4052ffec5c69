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


VOTE_VIEWS = 256
"""Views whose first returns vote at once for the hull's pieces (`object_hull`): bounded memory (tens of MB)."""
RETURN_MIN_VIEWS = 3
"""A hull cell holds the object's surface for `returns_box` where the first returns of at least this many views land
in it (those of one or two views: noise, or the glancing edge of a wide zone), or of one view in RETURN_VIEWS_PER_HIT
where that is fewer (at least one): of a 20 cm ball seen by 16 views, each view's nearest patch is its own, and
cells that 3 views' returns land in held a quarter of it."""
RETURN_VIEWS_PER_HIT = 64
RETURN_DEPTHS_M = (0.0, 0.005, 0.01, 0.015, 0.02)
"""How far (metres) beyond a zone's first-return onset `returns_box` looks for the surface that made it: a voxel's
steps through the first 2 cm of a surface seen at a slant."""
RETURN_DIRECTIONS = 256
"""Directions of each zone `returns_box` marches (a stride through the fit's candidate rays): 1.6 degrees apart in
the lcspc-sim sensor's 15-degree cone, about 1.4 cm at 0.5 m, against hull cells of 3-6 mm."""


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
    ok = np.isfinite(onset_m)
    dirs = zone_dirs[:, :: max(1, zone_dirs.shape[1] // 64)]
    votes = np.zeros(n + 1, np.int64)
    for a in range(0, len(poses), VOTE_VIEWS):
        views = slice(a, a + VOTE_VIEWS)
        votes += _piece_votes(lab, n, origin, voxel, poses[views], dirs, onset_m[views], ok[views], depths_m)
    keep = votes >= min_views * votes.max()
    keep[0] = False
    return keep[lab]


def returns_box(occupancy: np.ndarray, origin, voxel: float, poses: np.ndarray, zone_dirs: np.ndarray,
                onset_m: np.ndarray, pad_m: float) -> np.ndarray:
    """The carved occupancy (nz, ny, nx) cut to the box, grown by `pad_m` (metres), around the hull cells in which
    the first returns of at least RETURN_MIN_VIEWS views land (fewer of a capture of few views; the object's surface);
    the occupancy itself where no cell has them.

    Carving keeps whatever no view proved empty, and that includes the object's shadow: space that only views from
    its far side have in their fields, beyond their first returns. Views aimed at the floor under the object look into
    that space from its own side and carve it; views aimed at the object's middle, as a rig is set up, leave it: a
    teddy's hull spanned 54 cm for a 20 cm object, the SDF grid's box with it, and the fit's cells came out twice as
    coarse (4.8 mm against 2.3; Chamfer 1.80 mm against 0.94). Nothing in that shadow can be fitted: no histogram
    holds a return from it. zone_dirs (Z, D, 3) sensor frame, onset_m (V, Z) metres (NaN: nothing detected), poses
    (V, 4, 4), as for `object_hull`.
    """
    occ = np.asarray(occupancy, bool)
    hits = np.zeros(occ.size, np.int32)
    dirs = zone_dirs[:, :: max(1, zone_dirs.shape[1] // RETURN_DIRECTIONS)]
    ok = np.isfinite(onset_m)
    for a in range(0, len(poses), VOTE_VIEWS):
        views = slice(a, a + VOTE_VIEWS)
        np.add.at(hits, _cells_hit(occ.shape, origin, voxel, poses[views], dirs, onset_m[views], ok[views]), 1)
    surface = occ & (hits.reshape(occ.shape) >= min(RETURN_MIN_VIEWS, max(1, len(poses) // RETURN_VIEWS_PER_HIT)))
    if not surface.any():
        return occ.copy()
    idx = np.argwhere(surface)
    grow = int(np.ceil(pad_m / voxel))
    lo, hi = np.maximum(idx.min(axis=0) - grow, 0), idx.max(axis=0) + grow + 1
    cut = np.zeros_like(occ)
    cut[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = occ[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    return cut


def _cells_hit(shape, origin, voxel: float, poses: np.ndarray, dirs: np.ndarray, onset_m: np.ndarray,
               ok: np.ndarray) -> np.ndarray:
    """Flat indices into a grid of `shape` (nz, ny, nx), one per (view, cell) pair, of the cells that the points at
    each detected zone's onset plus RETURN_DEPTHS_M along its directions fall in (`_return_cells`'s arguments)."""
    v, i, good = _return_cells(shape, origin, voxel, poses, dirs, onset_m, ok, RETURN_DEPTHS_M)
    cells = i[good]
    size = int(np.prod(shape))
    flat = np.ravel_multi_index((cells[:, 2], cells[:, 1], cells[:, 0]), shape)
    return np.unique(np.broadcast_to(v[:, None], good.shape)[good] * size + flat) % size


def _piece_votes(lab: np.ndarray, n: int, origin, voxel: float, poses: np.ndarray, dirs: np.ndarray,
                 onset_m: np.ndarray, ok: np.ndarray, depths_m) -> np.ndarray:
    """(n + 1,) int: how many of these views land a point (`_return_cells`) in each piece of `lab` (labels 1..n, 0
    outside); a view counts once a piece. All of them at once: a loop over the views took 5.5 s of a 10,000-view
    capture's set-up."""
    v, i, good = _return_cells(lab.shape, origin, voxel, poses, dirs, onset_m, ok, depths_m)
    which = np.zeros(good.shape, np.int64)
    which[good] = lab[i[good][:, 2], i[good][:, 1], i[good][:, 0]]
    view_piece = np.unique(v[:, None] * (n + 1) + which)  # each (view, piece) once
    votes = np.bincount(view_piece % (n + 1), minlength=n + 1)
    votes[0] = 0
    return votes


def _return_cells(shape, origin, voxel: float, poses: np.ndarray, dirs: np.ndarray, onset_m: np.ndarray,
                  ok: np.ndarray, depths_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the first returns of these views land in a grid of `shape` (nz, ny, nx) of cell `voxel` (metres) from
    `origin`: the points at each detected zone's onset range plus each of `depths_m` along each of its directions.
    poses (v, 4, 4), each zone's directions dirs (Z, d, 3) in the sensor frame (turned into the world here, for these
    views alone: a capture's views at once held hundreds of megabytes), onset_m (v, Z) metres, ok (v, Z) where a
    return was detected. Returns (the view of each detected zone (k,), the points' cells (k, m, 3) as (x, y, z)
    indices, which of them lie in the grid (k, m))."""
    v, z = np.nonzero(ok)
    reach = onset_m[v, z][:, None] + np.asarray(depths_m, float)[None]  # (k, depths)
    world = np.einsum("vij,zdj->vzdi", poses[:, :3, :3], dirs)[v, z]  # (k, d, 3)
    p = poses[v, None, None, :3, 3] + world[:, None] * reach[:, :, None, None]  # (k, depths, d, 3)
    i = np.round((p - np.asarray(origin, float)) / voxel).astype(np.int64).reshape(len(v), p.shape[1] * p.shape[2], 3)
    good = np.all((i >= 0) & (i < np.array(shape[::-1])), axis=-1)
    return v, i, good


__all__ = ["HullConstraint", "hull_field", "object_hull", "returns_box"]
