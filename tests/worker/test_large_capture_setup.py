"""A large capture's set-up reads an evenly spread subset of its views (worker/carving/view_subset.py): carving and
the empty-space weights cost O(views x cells), training reads every view."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from spadscan.protocol.errors import CaptureError
from spadscan.worker.carving import view_subset
from spadscan.worker.carving.view_subset import MAX_SETUP_VIEWS, spread_views
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.fast import problem as fast_problem
from spadscan.worker.recon.fast.model import make_fast_model
from spadscan.worker.recon.fast.parts import empty_space
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.presets import preset_config
from spadscan.worker.recon.scene_data import load_scene
from worker_helpers import FAST_SMALL

pytestmark = pytest.mark.usefixtures("one_thread")


def sphere_poses(n: int, radius: float = 0.5) -> np.ndarray:
    """(n, 4, 4) sensor-to-world poses on a Fibonacci sphere, each looking at the origin (+z boresight)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    eye = radius * np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k, e in enumerate(eye):
        fwd = -e / np.linalg.norm(e)
        side = np.cross(fwd, [0.0, 0.0, 1.0] if abs(fwd[2]) < 0.9 else [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side)
        poses[k, :3, :3] = np.stack([side, np.cross(fwd, side), fwd], axis=1)
        poses[k, :3, 3] = e
    return poses


def covering_angle_deg(poses: np.ndarray, picked: np.ndarray) -> float:
    """The largest angle (degrees, seen from the origin) from any view to its nearest picked view."""
    u = poses[:, :3, 3] / np.linalg.norm(poses[:, :3, 3], axis=1, keepdims=True)
    cos = np.clip(u @ u[picked].T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.max(axis=1)).max()))


def test_a_large_capture_gives_max_views_spread_evenly_whatever_their_order():
    poses = sphere_poses(2000)
    # Ranked like an adaptive scan's views: from the top down, so its first views are one cap of the sphere.
    order = np.argsort(-poses[:, 2, 3], kind="stable")
    ranked = poses[order]
    picked = spread_views(ranked)
    assert len(picked) == MAX_SETUP_VIEWS == 256
    assert np.all(np.diff(picked) > 0)  # sorted, no view twice
    # 256 evenly spread views leave no view farther than about one spacing (sqrt(4 pi / 256): 12.7 degrees) from
    # one of them; the first 256 by rank leave the bottom of the sphere 150 degrees away.
    assert covering_angle_deg(ranked, picked) < 16.0
    assert covering_angle_deg(ranked, np.arange(256)) > 120.0
    # The same views in another order give the same subset.
    shuffle = np.random.default_rng(1).permutation(2000)
    again = spread_views(ranked[shuffle])
    assert sorted(shuffle[again].tolist()) == picked.tolist()
    assert np.array_equal(spread_views(ranked), picked)  # deterministic


def test_a_capture_of_at_most_max_views_passes_through_untouched():
    poses = sphere_poses(MAX_SETUP_VIEWS)
    assert np.array_equal(spread_views(poses), np.arange(MAX_SETUP_VIEWS))
    usable = np.ones((MAX_SETUP_VIEWS, 9), bool)
    usable[3] = False  # a view without data: still passed, as before
    assert np.array_equal(spread_views(poses, usable=usable), np.arange(MAX_SETUP_VIEWS))
    assert np.array_equal(spread_views(poses[:5], max_views=5), np.arange(5))


def test_views_without_data_are_never_picked_and_repeated_poses_are_picked_once():
    poses = sphere_poses(600)
    usable = np.ones((600, 9), bool)
    usable[::2] = False
    picked = spread_views(poses, max_views=100, usable=usable)
    assert len(picked) == 100 and np.all(picked % 2 == 1)
    few = np.zeros((600, 9), bool)
    few[:40] = True
    assert np.array_equal(spread_views(poses, max_views=100, usable=few), np.arange(40))
    same = np.tile(np.eye(4), (50, 1, 1))
    assert np.array_equal(spread_views(same, max_views=10), np.unique(spread_views(same, max_views=10)))
    assert len(spread_views(same, max_views=10)) == 10


def test_bad_poses_or_limits_are_refused_in_one_line():
    with pytest.raises(CaptureError, match="poses must be finite"):
        spread_views(np.zeros((10, 3, 4)))
    bad = sphere_poses(10)
    bad[2, 0, 3] = np.nan
    with pytest.raises(CaptureError, match="poses must be finite"):
        spread_views(bad)
    for limit in (0, -3, 2.5):
        with pytest.raises(CaptureError, match="view limit"):
            spread_views(sphere_poses(10), max_views=limit)


def _spy(monkeypatch, module, name: str, calls: list, views_of) -> None:
    """Replace module.name by a wrapper that records how many views each call was given."""
    real = getattr(module, name)

    def wrapper(*args, **kwargs):
        calls.append(views_of(*args, **kwargs))
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, wrapper)


@pytest.mark.parametrize("capture, work", [("cylinder_capture", "views_hearing"), ("table_capture", "view_coverage")])
def test_a_large_captures_set_up_reads_at_most_max_views_and_training_reads_them_all(capture, work, request,
                                                                                       monkeypatch):
    path = request.getfixturevalue(capture)  # 24 views without a table, 12 on one
    config = with_overrides(preset_config("fast"), FAST_SMALL)
    calls: dict[str, list] = {"carve": [], "weights": []}
    _spy(monkeypatch, fast_problem, "carve_scene", calls["carve"], lambda counts, poses, *a, **k: len(poses))
    _spy(monkeypatch, empty_space, work, calls["weights"], lambda points, poses, *a, **k: len(poses))

    whole = make_fast_model(load_scene(path), config, "cpu", RunPlan(steps=1, budget_s=None, seed=0))
    whole.step()
    views = whole.n_views
    assert calls == {"carve": [views], "weights": [views]} and whole.problem.setup_views is None
    assert "setup_views" not in whole.problem.notes

    monkeypatch.setattr(view_subset, "MAX_SETUP_VIEWS", 5)
    calls["carve"].clear()
    calls["weights"].clear()
    model = make_fast_model(load_scene(path), config, "cpu", RunPlan(steps=1, budget_s=None, seed=0))
    model.step()
    assert calls == {"carve": [5], "weights": [5]}
    assert model.problem.notes["setup_views"] == 5 and len(model.problem.setup_views) == 5
    assert model.n_views == views and model.problem.counts.shape[0] == views  # training keeps every view
    assert int(model.rays.count.numel()) == views * model.n_zones
    assert torch.isfinite(model.field.sdf).all()
