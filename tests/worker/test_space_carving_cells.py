"""Space carving's per-cell verdicts against the zones' own definitions, point by point.

`_classify_cells` decides with plane and cone distances on whole cells at once; here every verdict is checked on
points sampled over each cell's bounding sphere, with the sensor model's definition of a zone (a cone's half-angle,
a rect zone's tangent bounds) and of a range limit.
"""

from __future__ import annotations

import numpy as np
import pytest

from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker.carving.space_carving import DROP, KEEP, SPLIT, _classify_cells


def _in_zone(local: np.ndarray, zone) -> np.ndarray:
    """(..., 3) sensor-frame points -> bool: inside the zone, by its definition."""
    x, y, z = local[..., 0], local[..., 1], local[..., 2]
    if zone.kind == "cone":
        cos = (local @ np.asarray(zone.axis)) / np.linalg.norm(local, axis=-1)
        return cos >= np.cos(zone.half_angle_rad)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx, ty = x / z, y / z
    return (z > 0) & (tx >= zone.tan_x[0]) & (tx <= zone.tan_x[1]) & (ty >= zone.tan_y[0]) & (ty <= zone.tan_y[1])


def _sphere_points(centres, radius, n=96, seed=0):
    """(M, n + 1, 3): each centre and n points spread over its sphere of `radius`."""
    u = np.random.default_rng(seed).normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return np.concatenate([centres[:, None], centres[:, None] + radius * u[None]], axis=1)


def _empty_proof(points, poses, limit, sensor):
    """(M, views, zones) fraction of each cell's points that the zone saw empty: inside it and nearer than its
    limit."""
    frac = np.zeros((points.shape[0], len(poses), len(sensor.zones)))
    for v, pose in enumerate(poses):
        local = (points - pose[:3, 3]) @ pose[:3, :3]  # world -> sensor frame
        rng = np.linalg.norm(local, axis=-1)
        for z, zone in enumerate(sensor.zones):
            frac[:, v, z] = (_in_zone(local, zone) & (rng <= limit[v, z])).mean(axis=1)
    return frac


def _limits(rng, poses, sensor):
    """Ranges (metres) in front of which each zone saw nothing, as if an object 4-8 cm across sat at the origin
    that the views look at: cells near it are kept, cells far from it carved, the ones between undecided."""
    to_target = np.linalg.norm(poses[:, :3, 3], axis=1)[:, None]
    return to_target - rng.uniform(0.02, 0.04, size=(len(poses), len(sensor.zones)))


def _setting(preset, seed, half_width):
    """A sensor, 24 views of a hemisphere 0.3 m out, 1,500 cell centres uniform in a cube of `half_width` metres
    about the origin, and the zones' empty ranges (`_limits`)."""
    sensor = sensor_preset(preset)
    poses = fibonacci_hemisphere(24, 0.3, min_elevation_deg=10, max_elevation_deg=80)
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-half_width, half_width, size=(1500, 3))
    return sensor, poses, centres, _limits(rng, poses, sensor)


@pytest.mark.parametrize("preset", ["lcspc-sim", "tmf8820"])
def test_cell_verdicts_hold_point_by_point(preset):
    sensor, poses, centres, limit = _setting(preset, seed=1, half_width=0.08)
    radius = 0.01
    verdict = _classify_cells(centres, radius, poses, sensor, limit, final=False, min_views=0, edge_rad=0.0)
    counts = np.bincount(verdict, minlength=3)
    assert counts[DROP] > 50 and counts[KEEP] > 50 and counts[SPLIT] > 50, counts

    frac = _empty_proof(_sphere_points(centres, radius), poses, limit, sensor)
    # Carved: one zone of one view saw all of the cell empty.
    assert np.all(frac[verdict == DROP].max(axis=(1, 2)) == 1.0)
    # Kept: no zone of any view saw any of it empty.
    assert np.all(frac[verdict == KEEP].max(axis=(1, 2)) == 0.0)
    # Undecided (the test for "part of it" is conservative near a zone's corners, so no claim that part was seen
    # empty): nothing saw all of a slightly larger sphere empty, which would have carved it.
    split = verdict == SPLIT
    wider = _empty_proof(_sphere_points(centres[split], 1.2 * radius, seed=1), poses, limit, sensor)
    assert np.all(wider.max(axis=(1, 2)) < 1.0)


@pytest.mark.parametrize("preset", ["lcspc-sim", "tmf8820"])
def test_final_voxels_are_kept_unless_carved_and_seen_by_their_centre(preset):
    sensor, poses, centres, limit = _setting(preset, seed=2, half_width=0.1)
    radius = 0.004
    min_views = 3
    verdict = _classify_cells(centres, radius, poses, sensor, limit, final=True, min_views=min_views, edge_rad=0.0)
    assert not np.any(verdict == SPLIT)
    # Carved: all of the voxel's sphere was seen empty; points sample the sphere, so a voxel is surely carved when
    # a slightly larger sphere was.
    may_carve = _empty_proof(_sphere_points(centres, radius), poses, limit, sensor).max(axis=(1, 2)) == 1.0
    must_carve = _empty_proof(_sphere_points(centres, 1.2 * radius), poses, limit, sensor).max(axis=(1, 2)) == 1.0
    # Views whose zones hold the centre (a zone boundary exactly through a centre has measure zero).
    seen = np.zeros(len(centres), int)
    for v, pose in enumerate(poses):
        local = (centres - pose[:3, 3]) @ pose[:3, :3]
        seen += sum(_in_zone(local, zone) for zone in sensor.zones)
    unseen = seen < min_views
    assert must_carve.sum() > 50 and unseen.sum() > 10 and (~may_carve & ~unseen).sum() > 50
    dropped = verdict == DROP
    assert np.all(dropped[must_carve | unseen])
    assert not np.any(dropped[~may_carve & ~unseen])
