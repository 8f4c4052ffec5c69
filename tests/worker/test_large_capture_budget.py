"""A time budget keeps back what the end of a large capture's run costs (worker/budget.py, reconstruct.py): the
coverage count as the report makes it, on its spread views, timed by a probe on a few of them; the checks that read
every view of the capture (a floor that cuts the object, too little signal) run before training, in the set-up's
time, not in the end's."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.mesh_io import load_mesh_spec
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker import reconstruct
from spadscan.worker.budget import COMPLETION_SHARE, COVERAGE_DEFAULT_VIEWS, COVERAGE_S, SAFETY, EndCosts
from spadscan.worker.coverage import SPREAD_VIEWS, SurfaceViews, few_share
from worker_helpers import FAST_SMALL

pytestmark = pytest.mark.usefixtures("one_thread")


class Scene:
    """What the coverage count reads of a scene: 1,000 views, 100 of them without data."""

    def __init__(self, views: int = 1000):
        import torch

        self.poses = torch.as_tensor(fibonacci_hemisphere(views, 0.5, target=(0, 0, 0.05), min_elevation_deg=5))
        usable = np.ones((views, 1), bool)
        usable[::10] = False
        self.usable = torch.as_tensor(usable)
        self.sensor = sensor_preset("lcspc-sim")
        self.n_views = views


def test_the_coverage_count_is_kept_back_as_the_report_makes_it_on_its_spread_views(monkeypatch):
    """A 2000-view capture's report counted every view for every point (4 s; 20 s at 10,000 views) where nothing
    kept it back; it now counts SPREAD_VIEWS views for every point and the others for the few points alone, and the
    probe times a few of the spread views (1 ms a view on a fake clock here) and keeps back that count."""
    t, seen = [0.0], []

    def count(mesh, poses, sensor, usable=None):
        seen.append(len(poses))
        t[0] += 1e-3 * len(poses)
        return SurfaceViews(np.zeros((10, 3)), np.zeros((10, 3)), np.ones(10, int))  # every point seen: few none

    monkeypatch.setattr(reconstruct, "surface_views", count)
    costs = EndCosts()
    before = costs.end_s(256, None)
    reconstruct._probe_coverage(trimesh.creation.icosphere(), Scene(), costs, lambda: t[0])
    assert seen == [reconstruct.COVERAGE_PROBE_VIEWS] * 2  # a short probe is timed twice, the faster kept
    assert costs.coverage_s == pytest.approx(1e-3 * (SPREAD_VIEWS + COMPLETION_SHARE * (900 - SPREAD_VIEWS)))
    assert costs.end_s(256, None) == pytest.approx(before + SAFETY * (costs.coverage_s - COVERAGE_S))
    assert any(line.startswith(f"coverage {SPREAD_VIEWS} + 644 views") for line in costs.probed)

    small, seen[:] = Scene(40), []
    reconstruct._probe_coverage(trimesh.creation.icosphere(), small, costs, lambda: t[0])
    assert costs.coverage_s == pytest.approx(1e-3 * 40)  # every view counted for every point: no others


def test_the_other_views_are_kept_back_for_the_share_of_points_the_probe_finds_seen_by_few(monkeypatch):
    """The other views are counted for the points the spread views see fewer than FEW_VIEWS times: a flat plate seen
    close up by narrow views has all of them so (its count took 0.43 s where COMPLETION_SHARE kept back 0.10 s). The
    probe's own counts say what share that is (coverage.few_share): here 6 of 10 points seen by no probe view, 4 by
    one, a share between COMPLETION_SHARE and all of them."""
    t = [0.0]
    counts = np.array([0] * 6 + [1] * 4)

    def count(mesh, poses, sensor, usable=None):
        t[0] += 1e-3 * len(poses)
        return SurfaceViews(np.zeros((10, 3)), np.zeros((10, 3)), counts)

    monkeypatch.setattr(reconstruct, "surface_views", count)
    costs = EndCosts()
    reconstruct._probe_coverage(trimesh.creation.icosphere(), Scene(), costs, lambda: t[0])
    share = few_share(counts, reconstruct.COVERAGE_PROBE_VIEWS, SPREAD_VIEWS)
    assert COMPLETION_SHARE < share < 1.0
    assert costs.coverage_s == pytest.approx(1e-3 * (SPREAD_VIEWS + share * (900 - SPREAD_VIEWS)))
    assert any(line.startswith(f"coverage {SPREAD_VIEWS} + 644 views at {share:.2f}") for line in costs.probed)


def test_the_default_coverage_cost_grows_with_the_views_when_the_mesh_probe_fails():
    """COVERAGE_S is a 256-view figure: where the model has no surface to probe yet, a 1,000-view capture's default
    is that of its spread views and its others (at COMPLETION_SHARE), and a 40-view capture's is less."""

    class Model:
        def render_histograms(self, views):
            pass

        def extract_mesh(self, resolution):
            raise SpadscanError("no surface")

    per_view = COVERAGE_S / COVERAGE_DEFAULT_VIEWS
    for scene, want in ((Scene(), per_view * (SPREAD_VIEWS + COMPLETION_SHARE * (900 - SPREAD_VIEWS))),
                        (Scene(40), per_view * 40)):
        costs = EndCosts()
        reconstruct._probe_end_costs(Model(), scene.n_views, None, costs, lambda: 0.0, scene=scene)
        assert costs.coverage_s == pytest.approx(want)


def test_a_mesh_without_surface_leaves_the_default_coverage_cost():
    costs = EndCosts()
    reconstruct._probe_coverage(trimesh.Trimesh(), Scene(40), costs, lambda: 0.0)
    assert costs.coverage_s == EndCosts().coverage_s and costs.probed == []


def test_the_checks_that_read_every_view_run_before_training(tmp_path, monkeypatch):
    """At 10,000 views the floor's and the signal's checks read every view for 4 s after training, which the end's
    estimate did not hold: run before it, they are part of the set-up's time."""
    poses = fibonacci_hemisphere(6, 0.3, target=(0, 0, 0.05), min_elevation_deg=15)
    capture = simulate_capture(load_mesh_spec("builtin:sphere")[0], sensor_preset("lcspc-sim"), poses,
                               tmp_path / "cap", settings=SimSettings(rays_per_zone=64), progress=False)
    order = []
    for name in ("_floor_note", "_signal", "train"):
        real = getattr(reconstruct, name)
        monkeypatch.setattr(reconstruct, name, lambda *a, _real=real, _name=name, **k: order.append(_name) or _real(
            *a, **k))
    report = reconstruct.reconstruct_capture(capture, tmp_path / "out", steps=2, budget_s=600, device="cpu",
                                             overrides=FAST_SMALL, progress=False, threads=1)
    assert order == ["_floor_note", "_signal", "train"]
    assert any(line.startswith("coverage 6 + 0 views") for line in report["budget"]["timed"])
    assert report["coverage"]["median_views_estimated_from"] is None
