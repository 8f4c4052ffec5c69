"""The live fit grows with the views: a model rebuilt on more views continues from the last one's field
(`FastModel.warm_start`) instead of starting again from the hull, and never leaves the new, tighter hull."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch

from spadscan.worker.live.keep import LiveState, keep_the_better, scalars_of, use_field
from spadscan.worker.live.live_fit import LiveFit
from spadscan.worker.live.recoarse import RecoarsePolicy
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.fast.model import make_fast_model
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.presets import preset_config
from spadscan.worker.recon.scene_data import load_scene

from live_helpers import ReplayScan
from worker_helpers import FAST_SMALL

PLAN = RunPlan(steps=None, budget_s=None, seed=0)


def grown_scenes(source, tmp_path, first: int):
    """(scene of the first `first` views, scene of them all), read from one capture published in two goes."""
    scan = ReplayScan(source, tmp_path / "scan")
    scan.publish(first)
    few = load_scene(tmp_path / "scan")
    scan.publish(len(scan.poses))
    scan.finish()
    return few, load_scene(tmp_path / "scan")


def test_a_warm_model_starts_from_the_last_field_within_its_own_hull(cylinder_capture, tmp_path, one_thread):
    config = with_overrides(preset_config("fast"), FAST_SMALL)
    few, every = grown_scenes(cylinder_capture, tmp_path, 10)
    assert (few.n_views, every.n_views) == (10, 24)
    before = make_fast_model(few, config, "cpu", PLAN)
    for _ in range(12):  # past the refinement after 4 steps
        before.step()
    assert before.level == 1
    cold = make_fast_model(every, config, "cpu", PLAN)
    warm = make_fast_model(every, config, "cpu", PLAN)
    warm.warm_start(before.mesh_field(), before.level, before.level_steps)

    assert warm.level == before.level and warm.field.voxel == cold.field.voxel / 2
    assert warm.level_steps == before.level_steps == 8  # the learning-rate decay goes on where it was
    assert np.isclose(warm._grid_lr() / warm.field.voxel, before._grid_lr() / before.field.voxel)
    bound = warm.constraint.bound_for(warm.field)
    values = warm.field.sdf.detach()
    assert bool((values >= bound - 1e-6).all()), "the warm field leaves the new hull"
    with torch.no_grad():
        old = before.mesh_field().sample(warm.field.node_points())[None, None]
    inside = (warm.field.node_points() >= before.field.origin).all(-1) & \
             (warm.field.node_points() <= before.field.box_max).all(-1)
    kept = inside[None, None] & (old >= bound)
    assert kept.float().mean() > 0.3
    assert torch.allclose(values[kept], old[kept], atol=1e-5), "the warm field is not the last one's"
    # The cold start is the hull itself: the warm one has already left it where the first fit moved the surface.
    assert float((values - bound).abs().max()) > 2 * warm.field.voxel


def test_a_warm_model_explains_the_views_better_than_a_cold_one(cylinder_capture, tmp_path, one_thread):
    config = with_overrides(preset_config("fast"), FAST_SMALL)
    few, every = grown_scenes(cylinder_capture, tmp_path, 16)
    before = make_fast_model(few, config, "cpu", PLAN)
    for _ in range(40):
        before.step()
    cold = make_fast_model(every, config, "cpu", PLAN)
    warm = make_fast_model(every, config, "cpu", PLAN)
    warm.warm_start(before.mesh_field(), before.level)
    cold.refine()  # the same grid, so that only the start differs
    assert np.isclose(cold.field.voxel, warm.field.voxel)
    assert warm.deviance_all_views(seed=1) < 0.9 * cold.deviance_all_views(seed=1)


def test_a_final_run_that_fits_worse_than_the_live_state_is_not_published(cylinder_capture, tmp_path, one_thread):
    """The final run's field is thrown back to the hull (as a short run that went wrong would leave it): the live
    field explains the views better, and the model is left holding it, so that the mesh, the pictures and the
    metrics describe what is published. A final field that is the better one stays."""
    config = with_overrides(preset_config("fast"), FAST_SMALL)
    few, every = grown_scenes(cylinder_capture, tmp_path, 16)
    live = make_fast_model(few, config, "cpu", PLAN)
    for _ in range(40):
        live.step()
    field = live.mesh_field()
    live_field = type(field)(field.origin.numpy(), field.voxel, field.sdf.detach()[0, 0].clone())
    final = make_fast_model(every, config, "cpu", PLAN)
    final.refine()
    hull = final.constraint.bound_for(final.field)
    use_field(final, hull)  # the hull itself: nothing fitted
    kept = keep_the_better(final, LiveState(live_field, live.level, scalars_of(live)), log=lambda line: None)
    assert kept["published"]["mesh"] == "live"
    assert kept["published"]["deviance_live"] < kept["published"]["deviance_final"]
    assert not torch.allclose(final.mesh_field().sdf, hull), "the model holds the live field"
    assert final.deviance_all_views(0) == pytest.approx(kept["published"]["deviance_live"], abs=1e-4)

    held = final.mesh_field().sdf.detach().clone()
    again = keep_the_better(final, LiveState(live_field, live.level, scalars_of(live)),  # the final field is now
                            log=lambda line: None)                                         # the live one
    assert again["published"]["deviance_final"] == pytest.approx(again["published"]["deviance_live"], rel=1e-3)
    assert torch.allclose(final.mesh_field().sdf, held, atol=1e-6)
    # The same field with a far wrong albedo loses: the model keeps its own albedo with its own field.
    own = float(final.log_albedo.detach())
    dim = keep_the_better(final, LiveState(live_field, live.level, [torch.tensor(math.log(0.05))]),
                          log=lambda line: None)
    assert dim["published"]["mesh"] == "final" and float(final.log_albedo.detach()) == pytest.approx(own)
    assert torch.allclose(final.mesh_field().sdf, held, atol=1e-6)


def test_the_live_field_is_scored_on_its_own_grid_with_its_own_albedo(cylinder_capture, tmp_path, one_thread):
    """A final run from the hull that its budget ended on the coarse level, its albedo fitted to the hull's bloated
    surface: the live field, fitted further, is scored as it was fitted (its finer grid, its albedo), as well as it
    explains the views on its own model, and published; the model then holds its grid and albedo."""
    config = with_overrides(preset_config("fast"), FAST_SMALL)
    _, every = grown_scenes(cylinder_capture, tmp_path, 16)
    live = make_fast_model(every, config, "cpu", PLAN)
    for _ in range(40):
        live.step()
    assert live.level == 1
    use_field(live, live.mesh_field().sdf.detach().clone())  # the field it hands over
    own = live.deviance_all_views(0)
    state = LiveState(live.mesh_field(), live.level, scalars_of(live))
    final = make_fast_model(every, config, "cpu", PLAN)
    with torch.no_grad():
        final.log_albedo.fill_(math.log(0.5))
    kept = keep_the_better(final, state, log=lambda line: None)
    assert kept["published"]["deviance_live"] == pytest.approx(own, rel=1e-3)
    assert kept["published"]["mesh"] == "live"
    assert final.level == live.level
    assert float(final.log_albedo.detach()) == pytest.approx(float(live.log_albedo.detach()))


def test_recoarse_policy_wants_half_as_many_views_again_while_the_scan_is_young():
    policy = RecoarsePolicy()  # back to the coarse level at 1.5x the views, under half the plan
    assert not policy.due(coarse_views=8, views=11, planned=128)
    assert policy.due(coarse_views=8, views=12, planned=128)
    assert policy.due(coarse_views=40, views=63, planned=128)
    assert not policy.due(coarse_views=40, views=64, planned=128), "too late in the scan"
    assert policy.due(coarse_views=60, views=200, planned=None), "no plan known: growth alone decides"
    assert not RecoarsePolicy(growth=0).due(coarse_views=8, views=1000, planned=None), "growth 0: never"


def test_a_rebuild_goes_back_to_the_coarse_level_from_the_live_surface_when_the_views_have_grown_by_half(
        cylinder_capture, tmp_path, one_thread):
    config = with_overrides(preset_config("fast"), FAST_SMALL)
    scan = ReplayScan(cylinder_capture, tmp_path / "scan")
    fit = LiveFit(tmp_path / "scan", config, torch.device("cpu"), 0, log=lambda line: None)
    scan.publish(8)
    assert fit.rebuild(32) and fit.model.level == 0
    assert fit.train_steps(12) == 12 and fit.steps == 12  # past the refinement after 4 steps
    assert fit.model.level == 1

    scan.publish(4)  # 12 views: 1.5x the 8 the coarse level began with, under half of the 32 planned
    assert fit.rebuild(32)
    assert fit.model.level == 0 and fit.model.level_steps == 0 and fit.recoarsened == 1
    values = fit.model.field.sdf.detach()
    bound = fit.model.constraint.bound_for(fit.model.field)
    assert float((values - bound).abs().max()) > 2 * fit.model.field.voxel, "the coarse level starts from the hull"
    fit.train_steps(6)
    assert fit.model.level == 1 and fit.steps == 18
    steps = fit.model.level_steps

    scan.publish(5)  # 17 views: under 1.5x 12, so the fit goes on at the fine level
    assert fit.rebuild(32)
    assert (fit.model.level, fit.model.level_steps, fit.recoarsened) == (1, steps, 1)

    scan.publish(7)  # 24 views, 2x 12, but the scan is past half its plan
    assert fit.rebuild(32)
    assert (fit.model.level, fit.recoarsened) == (1, 1)
    assert fit.report()["coarse_restarts"] == 1

    assert fit.recent_steps_per_s() is None, "steps counted, not timed, so far"
    before = fit.steps
    for _ in range(2):
        fit.train(time.monotonic() + 0.1)
    rate = fit.recent_steps_per_s()
    assert rate == pytest.approx((fit.steps - before) / sum(s for _, s in fit.recent)) and rate > 0


def test_the_growth_that_sends_a_rebuild_back_to_the_coarse_level_counts_from_its_last_return(
        cylinder_capture, tmp_path, one_thread):
    """Half as many views again as the coarse level last began with, not as the first fit began with: 17 views
    after a return at 12 go on at the fine level, however young the scan (64 planned)."""
    config = with_overrides(preset_config("fast"), FAST_SMALL)
    scan = ReplayScan(cylinder_capture, tmp_path / "scan")
    fit = LiveFit(tmp_path / "scan", config, torch.device("cpu"), 0, log=lambda line: None)
    scan.publish(8)
    assert fit.rebuild(64) and fit.train_steps(12) == 12 and fit.model.level == 1
    scan.publish(4)  # 12 views: 1.5x 8
    assert fit.rebuild(64) and fit.model.level == 0 and fit.coarse_views == 12
    fit.train_steps(6)
    assert fit.model.level == 1
    scan.publish(5)  # 17 views: under 1.5x 12
    assert fit.rebuild(64) and (fit.model.level, fit.recoarsened, fit.coarse_views) == (1, 1, 12)


def test_the_final_run_starts_from_the_hull_while_the_live_fit_is_on_its_coarse_level(cylinder_capture, tmp_path,
                                                                                      one_thread):
    """A scan that ends before the live fit has left its coarse level (the demo's simulated scan takes 4 s), or just
    after: the final run's model starts from the carved hull, not from those few steps; once the fit has made as
    many steps on its last level as on its coarse one, the final run continues from it."""
    config = with_overrides(preset_config("fast"), FAST_SMALL)
    scan = ReplayScan(cylinder_capture, tmp_path / "scan")
    fit = LiveFit(tmp_path / "scan", config, torch.device("cpu"), 0, log=lambda line: None)
    scan.publish(len(scan.poses))
    scan.finish()
    every = load_scene(tmp_path / "scan")
    assert fit.rebuild(None) and fit.train_steps(2) == 2 and fit.model.level == 0
    assert not fit.continuable
    young = fit.warm_factory(True)(every, config, "cpu", PLAN)
    cold = make_fast_model(every, config, "cpu", PLAN)
    assert not young.warm_started and young.level == 0 and young.level_steps == 0
    assert torch.equal(young.field.sdf, cold.field.sdf), "the hull, as an ordinary run starts"

    fit.train_steps(4)  # the refinement after 4 steps, and 2 steps on the last level
    assert fit.model.level == 1 and not fit.continuable, "a fit that has only just left its coarse level"
    fit.train_steps(2)  # as many steps on the last level as the coarse level took
    assert fit.model.level_steps == 4 and fit.continuable
    grown = fit.warm_factory(True)(every, config, "cpu", PLAN)
    assert grown.warm_started and grown.level == 1 and grown.level_steps == fit.model.level_steps
    hull = fit.warm_factory(False)(every, config, "cpu", PLAN)
    assert not hull.warm_started and torch.equal(hull.field.sdf, cold.field.sdf), "told to start from the hull"
    live = fit.live_field().sdf.detach()
    assert torch.allclose(grown.field.sdf, torch.maximum(live, grown.constraint.bound_for(grown.field)), atol=1e-6)


def test_views_that_hold_no_return_are_not_fitted_and_the_live_status_says_why(tmp_path, one_thread):
    # The final run refuses such a capture; the live fit used to publish a noise mesh of it as "following the scan".
    from spadscan.protocol.live_status import read_status
    from spadscan.protocol.scenes import builtin_scene
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import simulate_capture
    from spadscan.worker.jobs import Job
    from spadscan.worker.live.follower import ScanFollower
    from spadscan.worker.live.job import LiveRun, LiveSettings

    sensor = sensor_preset("lcspc-sim").with_(zero_bin=-1000.0)  # every return before the first bin
    simulate_capture(builtin_scene("sphere"), sensor, fibonacci_hemisphere(8, 0.5, (0, 0, 0.1)), tmp_path / "dark",
                     progress=False)
    folder = tmp_path / "dark" / "recon" / "live"
    folder.mkdir(parents=True)
    run = LiveRun(Job(id="dark-fast", scan="dark", live=True, device="cpu"), tmp_path / "dark", folder,
                  ScanFollower(tmp_path / "dark"), LiveSettings(preview=False), log=lambda line: None)
    run.fit = LiveFit(tmp_path / "dark", with_overrides(preset_config("fast"), FAST_SMALL), torch.device("cpu"), 0,
                      lambda line: None)
    assert not run.fit.rebuild(8) and run.fit.model is None
    run.publish(run.follower.poll(), force=True)
    status = read_status(folder / "status.json")
    assert status.state == "waiting" and "no histogram holds a return above the noise" in status.note
    assert not (folder / "mesh.ply").exists()


def test_a_failed_first_fit_is_tried_again_only_with_more_views():
    from spadscan.worker.jobs import Job
    from spadscan.worker.live.follower import ScanProgress
    from spadscan.worker.live.job import LiveRun, LiveSettings

    class Fit:
        model, views_used = None, 0

    run = LiveRun(Job(id="s-fast", scan="s", live=True, device="cpu"), None, None, None, LiveSettings(min_views=8),
                  log=lambda line: None)
    run.fit, run.tried_views, run.last_rebuild = Fit(), 10, 0.0
    due = [run._refit_due(ScanProgress("running", None, views, 64, 1), 100.0) for views in (10, 11)]
    assert due == [False, True], "the same views would fail again: a capture load per poll for nothing"
