"""What both baselines share: meshing of point sets and the threshold calibration that the paper used (pick the
detection threshold with the best Chamfer distance)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import trimesh
from scipy.ndimage import binary_dilation, binary_fill_holes
from scipy.spatial import cKDTree

from spadscan.protocol.errors import CaptureError, MeshError

from ..carving.space_carving import occupancy_mesh

CALIBRATION_THRESHOLDS = (3.0, 4.0, 5.0, 7.0, 10.0, 15.0, 20.0, 30.0, 50.0, 80.0, 120.0, 200.0, 300.0)
"""Thresholds (noise standard deviations) tried by `calibrate`."""
CALIBRATION_POINTS = 100_000
"""Samples per mesh for the metrics during the search (the final metrics use the project's 300,000)."""
MIN_SURFACE_POINTS = 4
"""The fewest points `points_mesh` builds a surface through (a tetrahedron's corners)."""


def points_mesh(points: np.ndarray, method: str = "occupancy", spacing_m: float | None = None):
    """A closed surface through a point cloud (n, 3) metres.

    'occupancy': points splatted into a grid of spacing/4 voxels, dilated by half the median nearest-neighbour
    spacing, holes filled, marching cubes (a solid when the splats close up, a shell where they do not).
    'convex-hull': the points' convex hull. Returns a trimesh.Trimesh, or None when there are too few points.
    """
    pts = np.asarray(points, float)
    if len(pts) < MIN_SURFACE_POINTS:
        return None
    if method == "convex-hull":
        try:
            return trimesh.convex.convex_hull(pts)
        except Exception:  # qhull fails on flat or degenerate sets: no surface to speak of
            return None
    if method != "occupancy":
        raise CaptureError(f"surface method {method!r} is not 'occupancy' or 'convex-hull'")
    if spacing_m is None:
        d, _ = cKDTree(pts).query(pts, k=2)
        spacing_m = float(np.median(d[:, 1]))
    extent = float(np.max(np.ptp(pts, axis=0)))
    voxel = max(spacing_m / 4, extent / 400, 1e-4)  # at most ~400 voxels across
    rad = 2
    lo = pts.min(axis=0) - (rad + 3) * voxel
    shape = np.ceil((pts.max(axis=0) + (rad + 3) * voxel - lo) / voxel).astype(int)
    occ = np.zeros(shape, bool)
    idx = np.clip(np.floor((pts - lo) / voxel).astype(int), 0, shape - 1)
    occ[tuple(idx.T)] = True
    g = np.mgrid[-rad: rad + 1, -rad: rad + 1, -rad: rad + 1]
    occ = binary_fill_holes(binary_dilation(occ, np.linalg.norm(g, axis=0) <= rad))
    return occupancy_mesh(occ, lo + 0.5 * voxel, np.full(3, voxel), 1.0)


@dataclass
class Calibration:
    """The threshold search: the best threshold and every (threshold, Chamfer mm) tried."""

    threshold: float
    table: list[dict] = field(default_factory=list)


def calibrate(build: Callable[[float], object], truth, thresholds=None,
              progress: Callable[[float, float | None], None] | None = None,
              n_points: int = CALIBRATION_POINTS) -> Calibration:
    """Try each threshold (default CALIBRATION_THRESHOLDS): `build(threshold)` returns a mesh (or None); keep the
    one with the lowest Chamfer against `truth` (a ground_truth.GroundTruth), scored on `n_points` samples per
    mesh."""
    table, best = [], None
    for t in CALIBRATION_THRESHOLDS if thresholds is None else thresholds:
        start = time.monotonic()
        note = None
        try:
            mesh = build(float(t))
        except CaptureError as exc:  # e.g. no return this high above the noise: no surface at this threshold alone
            mesh, note = None, str(exc)
        chamfer = None
        if mesh is not None and len(mesh.faces) and mesh.area > 0:
            try:
                chamfer = truth.metrics(mesh, n_points=n_points).chamfer_mm
            except MeshError as exc:  # e.g. all of it under the table cut: nothing to score at this threshold
                note = str(exc)
        row = {"threshold": float(t), "chamfer_mm": chamfer, "seconds": round(time.monotonic() - start, 3)}
        table.append(row if note is None else {**row, "note": note})
        if chamfer is not None and (best is None or chamfer < best[1]):
            best = (float(t), chamfer)
        if progress is not None:
            progress(float(t), chamfer)
    if best is None:
        raise CaptureError("no threshold gave a surface to compare with the ground truth")
    return Calibration(best[0], table)
