"""Reprojection (the paper's baseline): each histogram's first return, back-projected along its zone's axis.

Every zone that detects a return gives one point: sensor origin + axis direction x range of the first return's
arrival (see `returns`). The returns are found with the pulse's leading-edge filter ('leading', as space carving
finds its onsets), not the matched filter: a pulse with a long tail (the TMF8820's) spreads a strong return ahead of
its arrival under the matched filter, so that bins of background alone cleared the threshold and a "first return"
landed up to 35 cm in front of the surface, behind the sensor even. A return at zero or negative range (noise in the
first bins) gives no point. Histograms no sensor could have produced (`usable`) give none either, and are left out
of the crosstalk unmixing of their view's other zones.

The points are written as a point cloud, and a surface is built from them (`common.points_mesh`: occupancy of the
splatted points and marching cubes, or their convex hull). A return comes from the nearest surface anywhere in the
zone's field of view, not from the axis, so the points are biased toward the sensor where the axis misses the
nearest surface: that is the baseline's weakness, kept as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spadscan.protocol.sensor_model import SensorModel

from ..carving.bounds import zone_axis
from ..carving.returns import DEFAULT_THRESHOLD, FirstReturns, check_inputs, first_returns
from .common import default_threshold, points_mesh

FILTER = "leading"
"""The detection filter reprojection finds its returns with (see the module docstring)."""


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
    behind_sensor: int = 0
    """First returns left out because their range was zero or negative (noise in the first bins)."""


def reprojection_returns(hists, sensor: SensorModel, threshold: float = DEFAULT_THRESHOLD,
                         usable: np.ndarray | None = None) -> FirstReturns:
    """The first returns reprojection reads: hists (n, zones, bins) counts; usable (n, zones) bool or None for all
    (histograms marked False detect nothing and stay out of the crosstalk unmixing)."""
    return first_returns(hists, sensor, threshold, FILTER, usable=usable)


def _reproject(hists, poses, sensor: SensorModel, threshold: float | None, floor_z: float | None,
               usable: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    """(points, view, zone, below the floor, behind the sensor): see `reproject_points`."""
    h, p = check_inputs(hists, poses, sensor)
    threshold = default_threshold(sensor) if threshold is None else threshold
    fr = reprojection_returns(h, sensor, threshold, usable)
    rng = fr.arrival_range_m(sensor)
    ahead = fr.detected & (rng > 0)  # NaN where nothing was detected compares False
    behind = int((fr.detected & ~ahead).sum())
    axes = np.stack([zone_axis(z) for z in sensor.zones])  # (zones, 3) sensor frame
    view, zone = np.nonzero(ahead)
    dirs = np.einsum("mij,mj->mi", p[view, :3, :3], axes[zone])
    pts = p[view, :3, 3] + dirs * rng[view, zone, None]
    keep = np.all(np.isfinite(pts), axis=1)
    finite = int(keep.sum())
    if floor_z is not None:
        keep &= pts[:, 2] >= floor_z - 0.005
    return pts[keep], view[keep], zone[keep], finite - int(keep.sum()), behind


def reproject_points(hists, poses, sensor: SensorModel, threshold: float | None = None,
                     floor_z: float | None = None,
                     usable: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(points (m, 3), view (m,), zone (m,), below) for every zone with a first return in front of the sensor
    (threshold None: the sensor's default, `common.default_threshold`, as `spadscan baseline` takes it);
    points below `floor_z` are left out (a floor the histograms do not show cannot hold a return, so they are
    noise), `below` counts them. usable (n, zones) bool, or None for all: histograms marked False give no point."""
    return _reproject(hists, poses, sensor, threshold, floor_z, usable)[:4]


def reprojection(hists, poses, sensor: SensorModel, *, threshold: float | None = None,
                 surface: str = "occupancy", floor_z: float | None = None,
                 usable: np.ndarray | None = None) -> Reprojection:
    """The reprojection baseline: back-projected first returns and a surface through them (threshold None: the
    sensor's default, `common.default_threshold`)."""
    threshold = default_threshold(sensor) if threshold is None else threshold
    pts, view, zone, below, behind = _reproject(hists, poses, sensor, threshold, floor_z, usable)
    return Reprojection(pts, view, zone, float(threshold), surface, points_mesh(pts, surface), below_floor=below,
                        behind_sensor=behind)
