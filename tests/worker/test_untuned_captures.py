"""Captures nobody tuned for: dropped frames seen by no view, an object cut by a floor it does not stand on, a
table height that is no number, a capture with no return or too few views for a baseline, a run whose one training
step overran its budget. Each says so in one line, in the report as on the terminal."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh

from spadscan.cli import main as cli_main
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.scenes import builtin_scene
from spadscan.protocol.schedules import fibonacci_hemisphere, look_at
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker import reconstruct
from spadscan.worker.carving.bounds import floor_cut_note, mesh_share_below, returns_below_floor
from spadscan.worker.end_of_run import RunFacts, warnings
from spadscan.worker.recon.scene_data import load_scene
from spadscan.worker.table_height import named_table

pytestmark = pytest.mark.usefixtures("one_thread")

SENSOR = sensor_preset("lcspc-sim")
SMALL = {"mesh_resolution": 32, "metrics_points": 5000, "early_stop": False}
BALL = trimesh.creation.icosphere(subdivisions=3, radius=0.08)  # centred on the origin: half of it below z = 0


def simulate(mesh, poses, path):
    return simulate_capture(mesh, SENSOR, poses, path, settings=SimSettings(rays_per_zone=512), progress=False)


@pytest.fixture(scope="module")
def ball_from_above(tmp_path_factory):
    return simulate(BALL, fibonacci_hemisphere(16, 0.5, min_elevation_deg=5), tmp_path_factory.mktemp("a") / "cap")


@pytest.fixture(scope="module")
def ball_from_below_too(tmp_path_factory):
    """16 views from above and 6 from steeply below (65-85 degrees under the ball)."""
    below = fibonacci_hemisphere(6, 0.5, min_elevation_deg=65, max_elevation_deg=85)
    below = np.stack([look_at(p[:3, 3] * [1, 1, -1], np.zeros(3)) for p in below])
    poses = np.concatenate([fibonacci_hemisphere(16, 0.5, min_elevation_deg=5), below])
    return simulate(BALL, poses, tmp_path_factory.mktemp("b") / "cap")


@pytest.fixture(scope="module")
def ball_on_floor(tmp_path_factory):
    return simulate(builtin_scene("sphere"), fibonacci_hemisphere(16, 0.5, target=(0, 0, 0.08), min_elevation_deg=5),
                    tmp_path_factory.mktemp("c") / "cap")


def floor_note(capture, truth=None, source="config"):
    scene = load_scene(capture)
    return reconstruct._floor_note(scene, {"floor_z_m": 0.0, "floor": source}, truth,
                                   reconstruct._as_carving_reads(scene))


# ---- 1. dropped frames ---------------------------------------------------------------------------------------------

def test_a_zone_without_data_sees_nothing_in_the_coverage():
    """A view whose histograms were dropped (all zero) saw nothing: counted as seeing, 29 dropped views of 48 made a
    one-sided scan look seen all round (15 % seen by few views, against 47 % with those views removed)."""
    from spadscan.worker.coverage import views_per_point

    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1)).apply_translation([0, 0, 0.05])
    eyes = [(0.5 * math.cos(math.radians(e)), 0.0, 0.05 + 0.5 * math.sin(math.radians(e))) for e in (10, 30, 50, 70)]
    poses = np.stack([look_at(eye, (0.0, 0.0, 0.05)) for eye in eyes])
    points = np.array([[0.05 + 1e-4, 0.0, 0.05]])
    normals = np.array([[1.0, 0.0, 0.0]])
    assert views_per_point(box, points, normals, poses, SENSOR)[0] == 4
    usable = np.array([[True], [False], [True], [False]])
    assert views_per_point(box, points, normals, poses, SENSOR, usable)[0] == 2
    scene = SimpleNamespace(poses=torch.as_tensor(poses), sensor=SENSOR, usable=torch.as_tensor(usable))
    assert reconstruct._coverage(None, box, scene, print).median_views <= 2


def test_dropped_histograms_are_a_warning_of_the_run_in_its_report_and_page(ball_on_floor, tmp_path):
    """'N of M histograms ... left out' reached the terminal only: a worker's job, which has none, lost it."""
    import shutil

    cap = tmp_path / "cap"
    shutil.copytree(ball_on_floor, cap)
    hists = cap / "chunk-000000" / "hists.npy"
    counts = np.load(hists)
    counts[:6] = 0
    np.save(hists, counts)
    lines = []
    report = reconstruct.reconstruct_capture(cap, tmp_path / "out", steps=3, device="cpu", progress=False,
                                             overrides=SMALL, threads=1, log=lines.append)
    note = f"{cap}: 6 of 16 histograms no sensor could have produced (6 all zero), left out"
    assert note in report["warnings"]
    assert note in json.loads((tmp_path / "out" / "report.json").read_text())["warnings"]
    assert "6 of 16 histograms no sensor could have produced" in (tmp_path / "out" / "report.html").read_text()
    assert not any("cuts the object" in w for w in report["warnings"]), "the ball stands on the floor"


# ---- 2. a floor that cuts the object -------------------------------------------------------------------------------

def test_a_ball_centred_on_the_origin_seen_from_below_warns_that_the_floor_cuts_it(ball_from_below_too):
    """The steep views from below have their first returns wholly under z = 0: no surface above the floor gave
    them. The fit would cut the ball flat there without a word."""
    note = floor_note(ball_from_below_too)
    assert note is not None and note.startswith("the floor at z = 0.000 m (field.floor_z, by default z = 0")
    assert "first returns come from wholly below it" in note and "--set field.floor_z=null" in note
    assert floor_note(ball_from_below_too, source="table") is None, "a table is seen in the histograms"
    assert "scene.floor_z in the capture's scan.json" in floor_note(ball_from_below_too, source="capture")


def test_a_ball_centred_on_the_origin_seen_from_above_warns_by_its_ground_truth(ball_from_above):
    """From above, the cut hemisphere gives the same first returns as the ball: the data cannot tell, and the ground
    truth the capture names can."""
    assert floor_note(ball_from_above) is None
    note = floor_note(ball_from_above, SimpleNamespace(mesh=BALL))
    assert note is not None and "of the ground truth's surface lies below it" in note
    assert mesh_share_below(BALL, 0.0) == pytest.approx(0.47, abs=0.03)


def test_an_object_standing_on_the_floor_gives_no_floor_warning(ball_on_floor):
    assert floor_note(ball_on_floor, SimpleNamespace(mesh=builtin_scene("sphere"))) is None
    scene = load_scene(ball_on_floor)
    below = returns_below_floor(scene.counts.double().numpy(), scene.poses.double().numpy(), SENSOR, 0.0)
    assert below.below == 0 and below.returns == 16 and not below.cuts
    assert floor_cut_note(0.0, "why", below, 0.0, "remedy") is None


def test_the_floor_warning_reaches_the_report_and_the_page(ball_from_below_too, tmp_path):
    report = reconstruct.reconstruct_capture(ball_from_below_too, tmp_path / "out", steps=3, device="cpu",
                                             progress=False, overrides=SMALL, threads=1)
    (line,) = [w for w in report["warnings"] if "cuts the object" in w]
    assert "first returns come from wholly below it" in line
    assert "cuts the object" in (tmp_path / "out" / "report.html").read_text()


def test_the_baselines_warn_of_the_floor_they_assume_and_not_without_one(ball_from_below_too, tmp_path, capsys):
    out = tmp_path / "carved"
    assert cli_main(["baseline", "space-carving", str(ball_from_below_too), "--out", str(out), "--no-gt"]) == 0
    (line,) = json.loads((out / "report.json").read_text())["warnings"]
    assert line.startswith("the floor at z = 0.000 m (a scene without a table: z = 0) cuts the object")
    assert "--no-floor" in line and f"warning: {line}" in capsys.readouterr().err
    assert "cuts the object" in (out / "report.html").read_text()
    assert cli_main(["baseline", "space-carving", str(ball_from_below_too), "--out", str(tmp_path / "none"),
                     "--no-gt", "--no-floor"]) == 0
    assert json.loads((tmp_path / "none" / "report.json").read_text())["warnings"] == []


# ---- 4. a table height that is no number ---------------------------------------------------------------------------

@pytest.mark.parametrize("table, key", [({"z": float("nan")}, "z"),
                                        ({"normal": [0, 0, 1], "offset": math.inf}, "offset")])
def test_a_table_height_that_is_no_finite_number_is_refused(table, key):
    with pytest.raises(CaptureError, match=rf"^scene\.table\.{key} (nan|inf) must be a finite number of metres$"):
        named_table(table)


@pytest.mark.parametrize("command", [["reconstruct", "--steps", "2", "--no-progress"], ["baseline", "space-carving"]])
def test_reconstruct_and_baseline_refuse_a_nan_table_in_one_line(ball_on_floor, tmp_path, capsys, command):
    """A table at z = NaN trained a whole run and then blamed the fit ('the fit diverged?'); the baseline wrote a
    result 'at z = nan m'."""
    import shutil

    cap = tmp_path / "cap"
    shutil.copytree(ball_on_floor, cap)
    manifest = json.loads((cap / "scan.json").read_text())
    manifest["scene"]["table"] = {"z": float("nan")}
    (cap / "scan.json").write_text(json.dumps(manifest))  # Python's json writes and reads NaN
    if command[0] == "reconstruct":
        args = ["reconstruct", str(cap), "--out", str(tmp_path / "out"), "--no-gt", "--device", "cpu"] + command[1:]
    else:
        args = command + [str(cap), "--out", str(tmp_path / "out"), "--no-gt"]
    assert cli_main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err == f"spadscan: error: {cap / 'scan.json'}: scene.table.z nan must be a finite number of metres"
    assert not (tmp_path / "out").exists()


# ---- 5. the points the metrics measured ----------------------------------------------------------------------------

def test_the_scoring_names_the_points_measured_when_the_deadline_cut_them():
    config = reconstruct.run_config("fast")
    assert reconstruct.final_scoring(config, 128, 286_000, measured=15_000) == \
        "final 128-cell mesh, 15,000 of 286,000 points"
    assert reconstruct.final_scoring(config, 128, 286_000, measured=286_000) == "final 128-cell mesh, 286,000 points"


# ---- 6. reprojection's hints ---------------------------------------------------------------------------------------

def test_reprojection_of_three_single_zone_views_says_more_views_not_a_lower_threshold(ball_on_floor, tmp_path,
                                                                                       capsys):
    import shutil

    cap = tmp_path / "cap"
    shutil.copytree(ball_on_floor, cap)
    chunk = cap / "chunk-000000"
    for name in ("hists.npy", "poses.npy"):
        np.save(chunk / name, np.load(chunk / name)[:3])
    meta = json.loads((chunk / "meta.json").read_text())
    meta["measurements"] = meta["measurements"][:3]
    (chunk / "meta.json").write_text(json.dumps(meta))
    manifest = json.loads((cap / "scan.json").read_text())
    manifest["planned_poses"] = 3
    (cap / "scan.json").write_text(json.dumps(manifest))
    if (cap / "schedule.npy").exists():
        np.save(cap / "schedule.npy", np.load(cap / "schedule.npy")[:3])
    assert cli_main(["baseline", "reprojection", str(cap), "--out", str(tmp_path / "out"), "--no-gt",
                     "--threshold", "1"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "its 3 view(s) of 1 zone(s) give at most 3 point(s), and a surface needs 4; scan more views" in err
    assert "lower --threshold" not in err


def test_a_capture_with_no_return_is_refused_by_reprojection_whatever_its_threshold(tmp_path, capsys):
    """Every view looks away from the object: following 'try a lower --threshold' on such a capture wrote a 4 m
    'surface' of noise without a warning."""
    eyes = fibonacci_hemisphere(8, 0.5, min_elevation_deg=10)[:, :3, 3]
    cap = simulate(builtin_scene("sphere"), np.stack([look_at(eye, 2 * eye) for eye in eyes]), tmp_path / "cap")
    for threshold in ("5", "3"):
        assert cli_main(["baseline", "reprojection", str(cap), "--out", str(tmp_path / "out"), "--no-gt",
                         "--threshold", threshold]) == 1
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith(f"spadscan: error: {cap}: no histogram holds a return above the noise"), err
    assert not (tmp_path / "out").exists()


# ---- 7. one training step over the budget --------------------------------------------------------------------------

def test_a_run_whose_training_overran_names_training_not_its_start_and_end():
    """The paper preset on a CPU: one step of 82 s against 2.8 s the budget left training, 159 s of 40 in all."""
    facts = RunFacts("budget", 1, None, [1.0], cpu_seconds=80.0, wall_seconds=81.8, budget_s=40.0, elapsed_s=159.0,
                     training_s=81.8, training_budget_s=2.8)
    (line,) = [w for w in warnings(facts) if w.startswith("the run took")]
    assert line.startswith("the run took 159.0 s of a 40 s time budget: training took 82 s of the 2.8 s the "
                           "budget left")
    assert "its start and its end" not in line and "--device cuda" in line
    spent = RunFacts("budget", 1, None, [1.0], cpu_seconds=80.0, wall_seconds=105.0, budget_s=40.0, elapsed_s=200.9,
                     training_s=105.0, training_budget_s=0.01)  # the set-up used the whole budget
    (line,) = [w for w in warnings(spent) if w.startswith("the run took")]
    assert "training took 105 s of the 0.01 s the budget left it, 105 s a step" in line
    ended = RunFacts("budget", 200, True, [1.0] * 200, cpu_seconds=6.0, wall_seconds=10.0, budget_s=30.0,
                     elapsed_s=41.4, training_s=20.0, training_budget_s=20.0)
    (line,) = warnings(ended)
    assert "its start and its end (the mesh, the pictures, the metrics) took longer" in line
