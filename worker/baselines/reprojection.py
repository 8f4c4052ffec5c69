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
                     floor_z: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(points (m, 3), view (m,), zone (m,), below) for every zone with a first return; points below `floor_z` are
    left out (a floor the histograms do not show cannot hold a return, so they are noise), `below` counts them."""
    h, p = check_inputs(hists, poses, sensor)
    fr = first_returns(h, sensor, threshold, "matched")
    rng = fr.arrival_range_m(sensor)
    axes = np.stack([zone_axis(z) for z in sensor.zones])  # (zones, 3) sensor frame
    view, zone = np.nonzero(fr.detected)
    dirs = np.einsum("mij,mj->mi", p[view, :3, :3], axes[zone])
    pts = p[view, :3, 3] + dirs * rng[view, zone, None]
    keep = np.all(np.isfinite(pts), axis=1)
    finite = int(keep.sum())
    if floor_z is not None:
        keep &= pts[:, 2] >= floor_z - 0.005
    return pts[keep], view[keep], zone[keep], finite - int(keep.sum())


def reprojection(hists, poses, sensor: SensorModel, *, threshold: float = DEFAULT_THRESHOLD,
                 surface: str = "occupancy", floor_z: float | None = None) -> Reprojection:
    """The reprojection baseline: back-projected first returns and a surface through them."""
    pts, view, zone, below = reproject_points(hists, poses, sensor, threshold, floor_z)
    return Reprojection(pts, view, zone, float(threshold), surface, points_mesh(pts, surface), below_floor=below)
