"""Reprojection (the paper's baseline): each histogram's first return, back-projected along its zone's axis.

Every zone that detects a return gives one point: sensor origin + axis direction x range of the first return's
arrival (matched-filter peak; see `returns`). The points are written as a point cloud, and a surface is built from
them (`common.points_mesh`: occupancy of the splatted points and marching cubes, or their convex hull). A return
comes from the nearest surface anywhere in the zone's field of view, not from the axis, so the points are biased
toward the sensor where the axis misses the nearest surface: that is the baseline's weakness, kept as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spadscan.protocol.sensor_model import SensorModel

from ..carving.bounds import zone_axis
from ..carving.returns import DEFAULT_THRESHOLD, check_inputs, first_returns
from .common import points_mesh


@dataclass
class Reprojection:
    """Back-projected first returns. points (m, 3) metres; view (m,) and zone (m,) say where each came from."""

    points: np.ndarray
    view: np.ndarray
    zone: np.ndarray
    threshold: float
    surface: str
    mesh: object | None
    """trimesh.Trimesh through the points, or None when there were too few."""
    below_floor: int = 0
    """First returns left out because they lay below the floor (a mesh of None with some: the floor's doing)."""


def reproject_points(hists, poses, sensor: SensorModel, threshold: float = DEFAULT_THRESHOLD,
                     floor_z: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (m, 3), view (m,), zone (m,)) for every zone with a first return; points below `floor_z` are left
    out (a floor the histograms do not show cannot hold a return, so they are noise)."""
    pts, view, zone, above = _reprojected(hists, poses, sensor, threshold, floor_z)
    return pts[above], view[above], zone[above]


def _reprojected(hists, poses, sensor: SensorModel, threshold: float, floor_z: float | None):
    """(points, view, zone) of every finite first return, and whether each lies above the floor (all: no floor)."""
    h, p = check_inputs(hists, poses, sensor)
    fr = first_returns(h, sensor, threshold, "matched")
    rng = fr.arrival_range_m(sensor)
    axes = np.stack([zone_axis(z) for z in sensor.zones])  # (zones, 3) sensor frame
    view, zone = np.nonzero(fr.detected)
    dirs = np.einsum("mij,mj->mi", p[view, :3, :3], axes[zone])
    pts = p[view, :3, 3] + dirs * rng[view, zone, None]
    finite = np.all(np.isfinite(pts), axis=1)
    pts, view, zone = pts[finite], view[finite], zone[finite]
    above = np.ones(len(pts), bool) if floor_z is None else pts[:, 2] >= floor_z - 0.005
    return pts, view, zone, above


def reprojection(hists, poses, sensor: SensorModel, *, threshold: float = DEFAULT_THRESHOLD,
                 surface: str = "occupancy", floor_z: float | None = None) -> Reprojection:
    """The reprojection baseline: back-projected first returns and a surface through them."""
    pts, view, zone, above = _reprojected(hists, poses, sensor, threshold, floor_z)
    pts, view, zone = pts[above], view[above], zone[above]
    return Reprojection(pts, view, zone, float(threshold), surface, points_mesh(pts, surface),
                        below_floor=int((~above).sum()))
