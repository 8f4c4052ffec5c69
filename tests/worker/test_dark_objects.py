"""A dark object's fit: its albedo read from the counts (`albedo_start`, `FastModel.counts_albedo`) and the
dark-restart part that starts its fit again from the hull with it; a bright object's fit as it was."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from spadscan.protocol.errors import ConfigError
from spadscan.worker.end_of_run import RunFacts, dark_warning, warnings
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.fast.albedo_start import ALBEDO_HI, albedo_for_total
from spadscan.worker.recon.fast.model import make_fast_model
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.presets import preset_config
from spadscan.worker.recon.scene_data import load_scene
from worker_helpers import FAST_SMALL, cylinder_mesh

pytestmark = pytest.mark.usefixtures("one_thread")


def saturating_total(background: float, signal: float, cycles: float = 1000.0):
    """A first-photon sensor's expected counts over `cycles` at albedo a: cycles x (1 - exp(-(background + a x
    signal))), non-decreasing in a and bounded by the cycles."""
    return lambda albedo: cycles * -math.expm1(-(background + albedo * signal))


@pytest.mark.parametrize("albedo", [0.002, 0.15, 1.0, 37.0])
def test_the_albedo_whose_expected_counts_total_the_measured_ones_is_found(albedo):
    total = saturating_total(0.01, 0.02)
    assert albedo_for_total(total, total(albedo)) == pytest.approx(albedo, rel=1e-6)


@pytest.mark.parametrize("measured", [0.0, 9.0, float("nan"), float("inf"), float("-inf")])
def test_counts_no_higher_than_the_background_or_not_finite_give_no_albedo(measured):
    assert albedo_for_total(saturating_total(0.01, 0.02), measured) is None  # the background alone: 9.95 counts


def test_counts_beyond_what_any_albedo_explains_give_the_highest_one():
    assert albedo_for_total(saturating_total(0.01, 1e-6), 999.0) == ALBEDO_HI


@pytest.fixture(scope="module")
def dark_and_bright(tmp_path_factory):
    """The same 16 views of worker_helpers.cylinder_mesh, of albedo 0.15 and 1 (LCSPCData's simulated sensor)."""
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    poses = fibonacci_hemisphere(16, 0.3, target=(0, 0, 0.03), min_elevation_deg=5)
    out = {}
    for name, albedo in (("dark", 0.15), ("bright", 1.0)):
        path = tmp_path_factory.mktemp("albedo") / name
        simulate_capture(cylinder_mesh(), sensor_preset("lcspc-sim"), poses, path,
                         settings=SimSettings(rays_per_zone=512, albedo=albedo), seed=3, progress=False)
        out[name] = load_scene(path)
    return out


def model_of(scene, **overrides):
    config = with_overrides(preset_config("fast"), {**FAST_SMALL, **overrides})
    return make_fast_model(scene, config, "cpu", RunPlan(steps=3, budget_s=None, seed=0))


CHECK_EARLY = {"parts.dark_restart.check_steps": 3, "parts.dark_restart.trend_steps": 1}


def test_the_counts_read_a_dark_object_about_as_many_times_darker_as_it_is(dark_and_bright):
    dark, bright = (model_of(dark_and_bright[name]).counts_albedo() for name in ("dark", "bright"))
    assert dark / bright == pytest.approx(0.15, rel=0.2)


def test_a_bright_objects_fit_is_not_restarted_and_trains_step_for_step_as_without_the_part(dark_and_bright):
    def trained(**overrides):
        model = model_of(dark_and_bright["bright"], **overrides)
        for _ in range(5):
            model.step()
        return model

    kept = trained(**CHECK_EARLY)
    part = kept.summary()["parts"]["dark_restart"]
    assert part["albedo_at_check"] > 0.45 and part["restarted_at_step"] is None
    off = trained(**{"parts.dark_restart.enabled": False})
    np.testing.assert_array_equal(kept.field.sdf.detach().numpy(), off.field.sdf.detach().numpy())
    assert kept.albedo() == off.albedo()


def test_a_dark_objects_fit_starts_again_from_the_hull_with_the_counts_albedo_once(dark_and_bright):
    model = model_of(dark_and_bright["dark"], **CHECK_EARLY, **{"parts.dark_restart.below": 1.0})
    start = model.field.sdf.detach().clone()
    for _ in range(2):
        model.step()
    assert not torch.equal(model.field.sdf.detach(), start)  # the first fit moves the grid before the check
    model.step()
    part = model.part("dark_restart")
    assert part.restarted_at_step == 3 and model.steps == 3 and model.level_steps == 0 and model.level == 0
    assert torch.equal(model.field.sdf.detach(), start)
    assert model.albedo() == pytest.approx(model.counts_albedo(), rel=1e-5) and model.albedo() < 0.5
    model.step()  # the new fit moves: a fresh optimiser on the new grid
    assert not torch.equal(model.field.sdf.detach(), start)
    for _ in range(3):  # past check_steps again: no second restart
        model.step()
    assert part.restarted_at_step == 3 and model.level_steps == 4 and model.part("dark_restart") is part
    assert model.summary()["parts"]["dark_restart"]["counts_albedo"] == pytest.approx(part.counts_albedo)


def test_a_warm_started_fit_is_never_restarted(dark_and_bright):
    first = model_of(dark_and_bright["dark"])
    model = model_of(dark_and_bright["dark"], **CHECK_EARLY, **{"parts.dark_restart.below": 1.0})
    model.warm_start(first.field, level=0)
    for _ in range(4):
        model.step()
    assert model.part("dark_restart").restarted_at_step is None and model.level_steps == 4


@pytest.mark.parametrize("key, value", [("check_steps", 0), ("check_steps", 2.5), ("check_steps", True),
                                        ("below", 0.0), ("below", 1.5), ("below", float("nan")), ("below", "x"),
                                        ("falling_below", -1.0), ("trend_steps", 0), ("trend_steps", 200)])
def test_bad_dark_restart_settings_are_refused_with_their_name(key, value):
    with pytest.raises(ConfigError, match=f"parts.dark_restart.{key}"):
        with_overrides(preset_config("fast"), {f"parts.dark_restart.{key}": value}).check()


def test_a_restart_starts_every_part_afresh_but_the_table_and_its_own_record(table_capture):
    scene = load_scene(table_capture)
    model = model_of(scene, **CHECK_EARLY, **{"parts.dark_restart.below": 1.0})
    before = {part.name: part for part in model.parts}
    for _ in range(3):
        model.step()
    assert model.part("dark_restart").restarted_at_step == 3
    kept = {name for name, part in before.items() if model.part(name) is part}
    assert kept == {"table", "dark_restart"}, kept
    assert [p.name for p in model.parts] == list(before)
    model.step()  # the kept table's parameters are in the new optimiser
    assert model.table is before["table"].table


def test_the_part_says_why_it_is_left_out_where_the_coarse_level_ends_before_its_check(dark_and_bright):
    model = model_of(dark_and_bright["dark"])  # FAST_SMALL: refined after 4 steps, the check at 200
    assert model.part("dark_restart") is None
    assert "parts.refinement.after_steps" in model.summary()["parts_left_out"]["dark_restart"]


def test_the_estimate_gives_no_albedo_for_a_model_that_renders_no_number():
    assert albedo_for_total(lambda albedo: float("nan"), 100.0) is None
    assert albedo_for_total(lambda albedo: 10.0 if albedo < 0.5 else float("nan"), 100.0) is None


def test_the_dark_line_says_the_albedo_and_the_restart_and_nothing_without_one():
    assert dark_warning(None) is None
    assert dark_warning({"restarted_at_step": None, "albedo_at_check": 0.6, "albedo": 0.95}) is None
    line = dark_warning({"restarted_at_step": 200, "albedo_at_check": 0.3, "counts_albedo": 0.09, "albedo": 0.13})
    assert line.startswith("the object is dark: its fitted albedo is 0.13") and "8x fewer photons" in line
    assert "started again from the hull at step 200" in line
    quiet = RunFacts(stopped_by="converged", steps=900, model_converged=True, data_terms=[1.0] * 900)
    assert warnings(quiet) == []
    assert warnings(replace(quiet, dark={"restarted_at_step": 200, "albedo": 0.13, "counts_albedo": 0.09})) == [line]
    # a restart whose fit came out bright says nothing of photons; one without a counts' reading does not claim it
    assert dark_warning({"restarted_at_step": 200, "counts_albedo": 0.3, "albedo": 0.97}) is None
    assert "read from the counts" not in dark_warning({"restarted_at_step": 200, "counts_albedo": None,
                                                       "albedo": 0.2})


@pytest.fixture(scope="module")
def dark_and_bright_balls(tmp_path_factory):
    """A 10 cm ball seen from 64 views at 0.5 m, of albedo 0.1 and 1 (LCSPCData's simulated sensor): the dark one's
    surface collapses before its albedo falls far (0.54 at step 200, and falling)."""
    import trimesh

    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    ball = trimesh.creation.icosphere(3, 0.1).apply_translation([0.0, 0.0, 0.1])
    poses = fibonacci_hemisphere(64, 0.5, target=(0, 0, 0.1), min_elevation_deg=5)
    out = {}
    for name, albedo in (("dark", 0.1), ("bright", 1.0)):
        out[name] = tmp_path_factory.mktemp("balls") / name
        simulate_capture(ball, sensor_preset("lcspc-sim"), poses, out[name],
                         settings=SimSettings(rays_per_zone=512, albedo=albedo), seed=3, progress=False)
    return out


@pytest.mark.slow
def test_reconstruct_of_a_dark_object_restarts_its_fit_and_says_so_and_of_a_bright_one_neither(
        dark_and_bright_balls, tmp_path):
    from spadscan.worker.reconstruct import reconstruct_capture

    # On the whole hull's grid, where the dark ball's albedo is still falling at step 200 (the rule this test is
    # for): aimed at its middle, its grid round the returns is finer, and there it is below `below` by then.
    run = {"steps": 205, "progress": False, "device": "cpu", "threads": 1, "gt": None,
           "overrides": {"mesh_resolution": 48, "early_stop": False, "field.hull_returns_pad_m": None}}
    parts, said = {}, {}
    for name, capture in dark_and_bright_balls.items():
        report = reconstruct_capture(capture, tmp_path / name, **run)
        parts[name] = report["model"]["parts"]["dark_restart"]
        said[name] = [w for w in report["warnings"] if w.startswith("the object is dark")]
    assert parts["bright"]["restarted_at_step"] is None and said["bright"] == [], parts
    dark = parts["dark"]
    assert dark["restarted_at_step"] == 200 and len(said["dark"]) == 1, parts
    # the fall that marks it: not below `below`, but under `falling_below` and lower than 50 steps before
    assert 0.45 < dark["albedo_at_check"] < min(0.6, dark["albedo_before"]), dark
    assert dark["counts_albedo"] < 0.1, dark  # the hull reads it low
