"""A large capture's views per surface point (worker/coverage.py): counted for every point on views spread over the
capture, completed with every view where that count is under FEW_VIEWS, so the shares seen by few views and by none
are those of counting every view; the counts above are estimates, and the report says from how many views."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from spadscan.protocol.schedules import look_at
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker import coverage
from spadscan.worker.coverage import FEW_VIEWS, SPREAD_VIEWS, summarize, surface_views, views_per_point

SENSOR = sensor_preset("lcspc-sim")


def scene():
    """A 10 cm box with a second one 20 cm behind it on -x, and 300 views: 296 spread over azimuths -70..70 degrees
    and elevations 5..75 on the +x side (the second box's faces towards +x hidden by the first from most of them),
    2 behind on -x (the boxes' far faces seen by those alone: too few), 2 more from above that hold no data."""
    mesh = trimesh.util.concatenate([trimesh.creation.box(extents=(0.1, 0.1, 0.1)).apply_translation([0, 0, 0.05]),
                                     trimesh.creation.box(extents=(0.06, 0.06, 0.06)).apply_translation(
                                         [-0.2, 0.0, 0.03])])
    rng = np.random.default_rng(2)
    az, el = np.radians(rng.uniform(-70, 70, 296)), np.radians(rng.uniform(5, 75, 296))
    eyes = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1) * 0.6
    eyes = np.concatenate([eyes, [[-0.9, 0.05, 0.3], [-0.9, -0.05, 0.25], [0.01, 0.0, 0.7], [0.0, 0.01, 0.7]]])
    poses = np.stack([look_at(eye, (-0.05, 0.0, 0.05)) for eye in eyes])
    usable = np.ones((len(poses), SENSOR.n_zones), bool)
    usable[-2:] = False  # dropped frames: they see nothing, counted or not
    return mesh, poses, usable


def test_the_shares_seen_by_few_views_and_by_none_are_those_of_every_view(monkeypatch):
    mesh, poses, usable = scene()
    whole = surface_views(mesh, poses, SENSOR, usable=usable, max_views=len(poses))
    assert whole.estimated_from is None
    exact = summarize(whole)
    assert 0.05 < exact.share_few and exact.share_unseen < exact.share_few, "some surface seen by 1-2 views"
    assert np.any((whole.counts > 0) & (whole.counts < FEW_VIEWS))

    calls = []
    real = coverage.views_per_point

    def counting(mesh, points, normals, poses, *args, **kwargs):
        calls.append((len(points), len(poses)))
        return real(mesh, points, normals, poses, *args, **kwargs)

    monkeypatch.setattr(coverage, "views_per_point", counting)
    spread = surface_views(mesh, poses, SENSOR, usable=usable, max_views=32)
    # Every point against the 32 spread views; the others (with data) only for the points those see under 3 times.
    assert calls[0] == (len(whole.points), 32)
    assert len(calls) == 2 and calls[1][0] < 0.6 * len(whole.points) and calls[1][1] == len(poses) - 2 - 32
    few = whole.counts < FEW_VIEWS
    assert np.array_equal(spread.counts[few], whole.counts[few])
    assert np.all(spread.counts[~few] >= FEW_VIEWS)
    estimate = summarize(spread)
    assert spread.estimated_from == estimate.estimated_from == 32
    assert (estimate.share_few, estimate.share_unseen, estimate.few_heights_m, estimate.points) == (
        exact.share_few, exact.share_unseen, exact.few_heights_m, exact.points)
    assert estimate.median_views == pytest.approx(exact.median_views, rel=0.25)
    assert estimate.to_dict()["median_views_estimated_from"] == 32 and exact.to_dict()[
        "median_views_estimated_from"] is None


def test_a_capture_of_at_most_the_spread_views_is_counted_whole_as_before():
    mesh, poses, usable = scene()
    few_poses, few_usable = poses[:: math.ceil(len(poses) / SPREAD_VIEWS)], usable[:: math.ceil(len(poses) / 256)]
    assert len(few_poses) <= SPREAD_VIEWS == 256
    samples = surface_views(mesh, few_poses, SENSOR, usable=few_usable)
    assert samples.estimated_from is None
    assert np.array_equal(samples.counts, views_per_point(mesh, samples.points, samples.normals, few_poses, SENSOR,
                                                          few_usable))
    # More views than the limit, but no more with data than it: every view with data is counted, nothing estimated.
    dropped = usable.copy()
    dropped[40:] = False
    samples = surface_views(mesh, poses, SENSOR, usable=dropped, max_views=40)
    assert samples.estimated_from is None
    assert np.array_equal(samples.counts, views_per_point(mesh, samples.points, samples.normals, poses, SENSOR,
                                                          dropped))
