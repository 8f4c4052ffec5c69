"""A live fit's rebuilds of a large capture carve from nearly the same views each time (view_subset.spread_views with
`keep`): the subset chosen afresh at each rebuild shared 29-48 % of its views with the one before."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from spadscan.worker.carving import view_subset
from spadscan.worker.carving.view_subset import spread_views
from spadscan.worker.live.live_fit import LiveFit
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.fast import problem as fast_problem
from spadscan.worker.recon.presets import preset_config

from live_helpers import ReplayScan
from test_large_capture_setup import covering_angle_deg, sphere_poses
from worker_helpers import FAST_SMALL


def test_a_subset_kept_as_views_arrive_stays_spread_and_changes_little():
    poses = sphere_poses(1200)
    ranked = poses[np.argsort(-poses[:, 2, 3], kind="stable")]  # an adaptive scan's order: from the top down
    kept, fresh_before = np.arange(256), None
    for n in range(356, 1201, 100):
        views = ranked[:n]
        fresh = spread_views(views)
        picked = spread_views(views, keep=kept)
        assert len(picked) == 256 and np.all(np.diff(picked) > 0)
        stayed = len(np.intersect1d(picked, kept)) / 256
        assert stayed >= 0.6, f"{n} views: {stayed:.0%} of the subset stayed"
        if fresh_before is not None:
            assert len(np.intersect1d(fresh, fresh_before)) / 256 < 0.6  # afresh, most of it changes
        assert covering_angle_deg(views, picked) < 1.15 * covering_angle_deg(views, fresh) + 0.5
        kept, fresh_before = picked, fresh


def test_kept_views_without_data_are_dropped_and_a_small_capture_passes_through():
    poses = sphere_poses(600)
    usable = np.ones((600, 9), bool)
    usable[:50] = False
    picked = spread_views(poses, max_views=100, usable=usable, keep=np.arange(0, 100))
    assert len(picked) == 100 and picked.min() >= 50
    assert np.array_equal(spread_views(poses[:100], max_views=100, keep=np.arange(5)), np.arange(100))
    # Without `keep`, the subset is farthest-point sampling as before.
    assert np.array_equal(spread_views(poses, max_views=100, keep=None), spread_views(poses, max_views=100))


def test_a_rebuild_keeps_the_views_the_last_one_carved_from(cylinder_capture, tmp_path, monkeypatch, one_thread):
    monkeypatch.setattr(view_subset, "MAX_SETUP_VIEWS", 6)
    asked = []
    real = fast_problem.spread_views
    monkeypatch.setattr(fast_problem, "spread_views", lambda *a, **k: asked.append(k.get("keep")) or real(*a, **k))
    config = with_overrides(preset_config("fast"), FAST_SMALL)
    scan = ReplayScan(cylinder_capture, tmp_path / "scan")
    fit = LiveFit(tmp_path / "scan", config, torch.device("cpu"), 0, log=lambda line: None)
    scan.publish(6)
    assert fit.rebuild(24) and asked == [None]
    assert np.array_equal(fit.setup_views(), np.arange(6)) and fit.model.problem.setup_views is None

    scan.publish(4)  # 10 views: a subset of 6, which keeps the 6 views carved from so far where it can
    assert fit.rebuild(24)
    assert np.array_equal(asked[-1], np.arange(6))
    first = fit.setup_views()
    assert len(first) == 6 and len(np.intersect1d(first, np.arange(6))) >= 2

    scan.publish(4)
    assert fit.rebuild(24)
    assert np.array_equal(asked[-1], first)
    assert len(np.intersect1d(fit.setup_views(), first)) >= 2
    assert fit.model.problem.notes["setup_views"] == 6


@pytest.mark.parametrize("keep", [None, np.arange(3)])
def test_a_capture_of_at_most_max_views_is_set_up_whole_whatever_is_kept(keep):
    poses = sphere_poses(view_subset.MAX_SETUP_VIEWS)
    assert np.array_equal(spread_views(poses, keep=keep), np.arange(view_subset.MAX_SETUP_VIEWS))
