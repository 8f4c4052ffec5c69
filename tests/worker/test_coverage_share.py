"""The share of a large capture's surface points that its coverage count completes with every view (those its spread
views see fewer than FEW_VIEWS times), estimated from a probe of a few of the spread views (worker/coverage.py
`few_share`), so that the time budget keeps back what that count takes. A point no probe view sees was once counted
as completed: most such points lie between the probe's views, and many spread views see them."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from spadscan.protocol.scenes import builtin_scene
from spadscan.protocol.schedules import fibonacci_hemisphere, look_at
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker.carving.view_subset import spread_views
from spadscan.worker.coverage import FEW_VIEWS, counted_views, few_share, surface_views, views_per_point
from spadscan.worker.reconstruct import COVERAGE_PROBE_VIEWS


def probe_and_truth(mesh, poses: np.ndarray, sensor) -> tuple[float, float, float]:
    """(old estimate, few_share's, the true share): the probe as the budget makes it (COVERAGE_PROBE_VIEWS of the
    spread views, spread among them) and the share of points the spread views see fewer than FEW_VIEWS times."""
    spread, others = counted_views(poses)
    assert len(spread) < len(poses) and others > 0
    timed = spread[spread_views(poses[spread], COVERAGE_PROBE_VIEWS)]
    probe = surface_views(mesh, poses[timed], sensor, n_points=2000)
    spread_count = views_per_point(mesh, probe.points, probe.normals, poses[spread], sensor)
    old = float(np.mean(probe.counts * (len(spread) / len(timed)) < FEW_VIEWS))  # each count scaled up
    return old, few_share(probe.counts, len(timed), len(spread)), float(np.mean(spread_count < FEW_VIEWS))


def test_points_between_the_probe_views_are_not_all_counted_as_seen_by_few():
    """A ball seen from 25 cm by 1,000 views in a 15-degree cone: each view sees a patch of it, so most points lie
    between the 8 probe views (seen by none of them) and yet in the patches of many of the 256 spread views. Counting
    every such point as completed kept back 0.64 of the completion where 0.24 was used."""
    poses = fibonacci_hemisphere(1000, 0.25, target=(0, 0, 0.08), min_elevation_deg=5)
    old, new, true = probe_and_truth(builtin_scene("sphere"), poses, sensor_preset("lcspc-sim"))
    assert 0.15 < true < 0.35
    assert old > true + 0.3  # the old estimate's error
    assert new == pytest.approx(true, abs=0.1)


def test_a_flat_plate_seen_close_up_is_all_completed():
    """Narrow views 2 cm over a 30 cm plate each see a spot of it: every point is seen by fewer than FEW_VIEWS of the
    spread views, and the estimate says so."""
    plate = trimesh.creation.box(extents=(0.3, 0.3, 0.01)).apply_translation([0, 0, 0.005])
    xy = np.random.default_rng(0).uniform(-0.15, 0.15, (1000, 2))
    poses = np.stack([look_at((x, y, 0.02), (x + 0.02, y, 0.0), up=(0, 1, 0)) for x, y in xy])
    old, new, true = probe_and_truth(plate, poses, sensor_preset("tmf8820"))
    assert true > 0.99
    assert new > 0.95


def test_points_the_probe_sees_often_are_not_few_and_a_whole_probe_is_exact():
    assert few_share(np.full(50, FEW_VIEWS), 8, 256) == 0.0  # seen FEW_VIEWS times already
    assert few_share(np.full(50, 8), 8, 256) == 0.0
    assert few_share(np.array([0, 1, 2, FEW_VIEWS]), 8, 8) == 0.75  # every spread view probed: as counted
    assert few_share(np.array([0, 1, 2, FEW_VIEWS]), 8, 4) == 0.75
    assert few_share(np.array([], int), 8, 256) == 0.0
    assert few_share(np.array([0, 1]), 0, 256) == 0.0


def test_the_estimate_follows_what_the_probe_sees():
    """Where the probe views see much of the surface, a point none of them sees is likely seen by enough spread
    views; where they see almost nothing, it is not; and fewer probe sightings never mean a smaller share."""
    mostly_seen = np.array([0] * 10 + [4] * 90)
    hardly_seen = np.array([0] * 99 + [1])
    assert few_share(mostly_seen, 8, 256) < 0.05
    assert few_share(hardly_seen, 8, 256) > 0.9
    shares = [few_share(np.array([k] * 20 + [2] * 80), 8, 256) for k in (0, 1, 2)]
    assert shares[0] >= shares[1] >= shares[2]


@pytest.mark.parametrize("counts", [np.zeros(10_000, int), np.full(10_000, 8), np.array([0, 8, np.nan, -3, 99.0])])
def test_the_estimate_stays_a_share_on_extremes(counts):
    for views_of in (9, 256, 100_000):
        share = few_share(counts, 8, views_of)
        assert np.isfinite(share) and 0.0 <= share <= 1.0
