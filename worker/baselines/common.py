"""What both baselines share: zone axes, scene bounds from the first returns, meshing of point sets, metrics and
the threshold calibration that the paper used (pick the detection threshold with the best Chamfer distance)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from spadscan.protocol.errors import CaptureError
from spadscan.protocol.sensor_model import SensorModel, Zone

from .returns import FirstReturns

CALIBRATION_THRESHOLDS = (3.0, 4.0, 5.0, 7.0, 10.0, 15.0, 20.0, 30.0, 50.0, 80.0, 120.0, 200.0, 300.0)
"""Thresholds (noise standard deviations) tried by `calibrate`."""
CALIBRATION_POINTS = 100_000
"""Samples per mesh for the metrics during the search (the final metrics use the project's 300,000)."""


def zone_axis(zone: Zone) -> np.ndarray:
    """(3,) unit vector in the sensor frame: a cone's axis, or the direction to a rect zone's centre."""
    if zone.kind == "cone":
        a = np.asarray(zone.axis, float)
    else:
        a = np.array([0.5 * (zone.tan_x[0] + zone.tan_x[1]), 0.5 * (zone.tan_y[0] + zone.tan_y[1]), 1.0])
    return a / np.linalg.norm(a)


def zone_edges(zone: Zone, n: int = 8) -> np.ndarray:
    """(m, 3) unit directions on the edge of a zone's field of view, plus its axis (sensor frame)."""
    if zone.kind == "cone":
        a = zone_axis(zone)
        u = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        v = np.cross(a, u)
        phi = np.linspace(0, 2 * np.pi, n, endpoint=False)[:, None]
        c, s = math.cos(zone.half_angle_rad), math.sin(zone.half_angle_rad)
        dirs = c * a + s * (np.cos(phi) * u + np.sin(phi) * v)
    else:
        dirs = np.array([[x, y, 1.0] for x in zone.tan_x for y in zone.tan_y])
    dirs = np.vstack([dirs, zone_axis(zone)])
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def scene_bounds(returns: FirstReturns, poses: np.ndarray, sensor: SensorModel, *, pad: float = 0.1,
                 floor_z: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A box (min (3,), max (3,), metres) around everything the zones saw: the footprints of the first returns.

    Each detected zone contributes its field of view's edge and axis directions at its first return's range; the box
    is grown by `pad` times its size on every side. Raises CaptureError when no zone saw anything.
    """
    rng = returns.arrival_range_m(sensor)
    pts = []
    for z, zone in enumerate(sensor.zones):
        ok = returns.detected[:, z]
        if not ok.any():
            continue
        dirs = zone_edges(zone)  # (m, 3)
        world = np.einsum("nij,mj->nmi", poses[ok, :3, :3], dirs)  # (k, m, 3)
        pts.append((poses[ok, None, :3, 3] + world * rng[ok, z, None, None]).reshape(-1, 3))
    if not pts:
        raise CaptureError("no histogram holds a return above the threshold: nothing to reconstruct")
    allp = np.concatenate(pts)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    size = np.maximum(hi - lo, 1e-3)
    lo, hi = lo - pad * size, hi + pad * size
    if floor_z is not None:
        lo[2] = max(lo[2], floor_z - 0.02 * size[2])
        if hi[2] <= lo[2]:
            raise CaptureError(f"every return lies below the floor z = {floor_z} m")
    return lo, hi


def cube_around(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smallest cube with the same centre that holds the box (cubic voxels on an R^3 grid)."""
    c, half = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo))
    return c - half, c + half


def points_mesh(points: np.ndarray, method: str = "occupancy", spacing_m: float | None = None):
    """A closed surface through a point cloud (n, 3) metres.

    'occupancy': points splatted into a grid of spacing/4 voxels, dilated by half the median nearest-neighbour
    spacing, holes filled, marching cubes (a solid when the splats close up, a shell where they do not).
    'convex-hull': the points' convex hull. Returns a trimesh.Trimesh, or None when there are too few points.
    """
    import trimesh
    from scipy.ndimage import binary_dilation, binary_fill_holes
    from scipy.spatial import cKDTree

    from .space_carving import occupancy_mesh

    pts = np.asarray(points, float)
    if len(pts) < 4:
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
        mesh = build(float(t))
        chamfer = None
        if mesh is not None and len(mesh.faces) and mesh.area > 0:
            chamfer = truth.metrics(mesh, n_points=n_points).chamfer_mm
        table.append({"threshold": float(t), "chamfer_mm": chamfer, "seconds": round(time.monotonic() - start, 3)})
        if chamfer is not None and (best is None or chamfer < best[1]):
            best = (float(t), chamfer)
        if progress is not None:
            progress(float(t), chamfer)
    if best is None:
        raise CaptureError("no threshold gave a surface to compare with the ground truth")
    return Calibration(best[0], table)
