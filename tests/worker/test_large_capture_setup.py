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


def look_at(eye, target) -> np.ndarray:
    """A sensor-to-world pose at `eye` (metres) whose +z boresight points at `target`."""
    fwd = np.asarray(target, float) - eye
    fwd /= np.linalg.norm(fwd)
    side = np.cross(fwd, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([side, np.cross(fwd, side), fwd], axis=1)
    pose[:3, 3] = eye
    return pose


@pytest.fixture(scope="module")
def clustered_rod(tmp_path_factory):
    """A 30 cm rod seen by 24 views spread over a hemisphere and by 40 clustered on its top (as an adaptive scan
    gathers views where the fit is unsure): farthest-point sampling gives the cluster one pick of 16."""
    import trimesh

    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    rod = trimesh.creation.cylinder(radius=0.03, height=0.30, sections=48)
    rod.apply_translation([0, 0, 0.15])
    wide = fibonacci_hemisphere(24, 0.3, target=(0, 0, 0.03), min_elevation_deg=5)
    rng = np.random.default_rng(0)
    cluster = np.stack([look_at(np.array([0.25, 0.0, 0.30]) + rng.normal(0, 0.01, 3), (0, 0, 0.27))
                        for _ in range(40)])
    path = tmp_path_factory.mktemp("rod") / "rod"
    simulate_capture(rod, sensor_preset("lcspc-sim"), np.concatenate([wide, cluster]), path,
                     settings=SimSettings(rays_per_zone=64), seed=3, progress=False)
    top = trimesh.sample.volume_mesh(rod, 20000)
    return path, top[top[:, 2] > 0.22]


@pytest.mark.parametrize("real", [False, True])  # a real capture keeps no space behind its first returns
def test_a_part_only_a_cluster_of_views_sees_stays_in_a_subsets_hull(clustered_rod, real, monkeypatch):
    """Space fewer than MIN_VIEWS views see is dropped as never scanned: counted among the subset's 16 views, of
    which one is the cluster's, the rod's top fell out of the hull (0 % of it inside), which the fit cannot leave."""
    path, top = clustered_rod
    scene = load_scene(path)
    scene.real = real
    fc = preset_config("fast").field
    counts, sensor = fast_problem._carving_views(scene)
    poses = scene.poses.double().numpy()
    monkeypatch.setattr(view_subset, "MAX_SETUP_VIEWS", 16)
    views = fast_problem._setup_views(poses, scene)
    assert len(views) == 16 and int(np.sum(views >= 24)) <= 2, "the cluster gets a pick or two"
    hull = fast_problem._carve(scene, counts, poses, sensor, fc, fc.floor_z, False, views=views)
    idx = np.round((top - hull.origin) / hull.voxel_m).astype(int)
    inside = np.all((idx >= 0) & (idx < np.array(hull.occupancy.shape)), axis=1)
    inside[inside] = hull.occupancy[tuple(idx[inside].T)]
    assert inside.mean() > 0.9, f"{inside.mean():.0%} of the rod's top is inside the hull"


def test_a_large_captures_deviance_is_scored_on_its_set_up_views(cylinder_capture, monkeypatch):
    """The openings' round of proposals scores the field up to four times: over every view of a 10,000-view capture
    that took 49 s at step 150; over the spread set-up views, 1.4 s. A capture of up to MAX_SETUP_VIEWS views is
    scored on every view, as before."""
    config = with_overrides(preset_config("fast"), FAST_SMALL)
    rendered = []

    def scored(model) -> float:
        real = model._rates
        monkeypatch.setattr(model, "_rates", lambda views, **k: rendered.extend(views.tolist()) or real(views, **k))
        return model.deviance_all_views(7)

    whole = make_fast_model(load_scene(cylinder_capture), config, "cpu", RunPlan(steps=1, budget_s=None, seed=0))
    every = scored(whole)
    assert sorted(rendered) == list(range(whole.n_views))

    monkeypatch.setattr(view_subset, "MAX_SETUP_VIEWS", 5)
    rendered.clear()
    model = make_fast_model(load_scene(cylinder_capture), config, "cpu", RunPlan(steps=1, budget_s=None, seed=0))
    subset = scored(model)
    assert sorted(rendered) == model.problem.setup_views.tolist() and len(rendered) == 5
    assert math.isfinite(subset) and subset > 0 and math.isfinite(every)
