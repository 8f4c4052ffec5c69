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

from ..carving.returns import DEFAULT_THRESHOLD
from ..carving.space_carving import occupancy_mesh

CALIBRATION_THRESHOLDS = (3.0, 4.0, 5.0, 7.0, 10.0, 15.0, 20.0, 30.0, 50.0, 80.0, 120.0, 200.0, 300.0)
"""Thresholds (noise standard deviations) tried by `calibrate`."""
SENSOR_THRESHOLDS = {"tmf8820": 20.0}
"""Default detection threshold (noise standard deviations) of the baselines per sensor model name; others take
`returns.DEFAULT_THRESHOLD` (5). Chosen by measurement, not derived from a capture's histograms: the z-scores' own
noise floor says nothing of what passes for a return on a TMF8820 (its simulated captures dip 7-9 deviations below
zero, the real pyramid 740: reference and crosstalk peaks, not noise). At 5 on simulated TMF8820 captures, zones that
see nothing clear 5 deviations (7 of 137 empty zones of a mug's 48 views, up to 6.8), and the matched filter's long
tail puts returns in front of the sensor: space carving's box grew to 1 m and so did its hull (builtin mug, Chamfer
177 mm with 48 views, 222 mm with 128; 123 and 158 mm at 10). At 20: 24.4 and 19.8 mm, the real pyramid 36.0 (37.6
at 5), and reprojection gains too (the mug 16.4 -> 15.2, the pyramid 8.95 -> 8.85); 30 gained at most 1.4 mm more,
and a higher threshold only risks faint, thin parts. The lcspc sensor keeps 5: its simulated captures dip 3
deviations at most, and 5 gives the dataset's figures (benchmarks/RESULTS.md)."""
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


def default_threshold(sensor) -> float:
    """The baselines' detection threshold for a capture of `sensor` (a SensorModel) when none is given: its entry in
    SENSOR_THRESHOLDS, else `returns.DEFAULT_THRESHOLD`."""
    return float(SENSOR_THRESHOLDS.get(str(sensor.name).lower(), DEFAULT_THRESHOLD))


def threshold_edge(threshold, tried) -> str | None:
    """Where a calibrated threshold lies among those tried: 'lowest' or 'highest' when it is one of the ends (a
    threshold beyond that end, never tried, may have done better), 'only' when a single one was tried, None when it
    lies between two it beat or no threshold was tried."""
    tried = sorted({float(t) for t in tried if isinstance(t, (int, float))})
    if threshold is None or not tried:
        return None
    if len(tried) == 1:
        return "only"
    if float(threshold) <= tried[0]:
        return "lowest"
    if float(threshold) >= tried[-1]:
        return "highest"
    return None


@dataclass
class Calibration:
    """The threshold search: the best threshold and every (threshold, Chamfer mm) tried."""

    threshold: float
    table: list[dict] = field(default_factory=list)

    def edge(self) -> str | None:
        """'lowest' or 'highest' when the best threshold is that end of the two or more tried (one beyond it, never
        tried, may do better), else None."""
        edge = threshold_edge(self.threshold, [row["threshold"] for row in self.table])
        return None if edge == "only" else edge

    def edge_note(self) -> str | None:
        """One line saying that the best threshold lies at an end of the range tried, or None."""
        edge = self.edge()
        if edge is None:
            return None
        tried = sorted({row["threshold"] for row in self.table})
        beyond = "below" if edge == "lowest" else "above"
        return (f"the calibrated threshold {self.threshold:g} is the {edge} of those tried ({tried[0]:g} to "
                f"{tried[-1]:g}): the best may lie {beyond} it, outside the range searched (try --threshold "
                f"values {beyond} it and compare)")


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
