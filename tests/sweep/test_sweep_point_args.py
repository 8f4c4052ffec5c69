"""A point hands its parameters to the heavy calls in the right places: the seed to the simulation and to the
reconstruction, the point counts and thresholds to the baselines, [metrics] points to the presets; and the dry run
counts a failed point among those to run. The heavy calls are stubbed: these tests only look at what they are given."""

from __future__ import annotations

import json

from spadscan.cli import main
from spadscan.sweep import point
from spadscan.sweep.plan import make_plan
from spadscan.sweep.spec import load_spec
from spadscan.sweep.store import SweepDir

from sweep_helpers import write_tiny
from test_sweep_store import fake_result

SEED = 4242
METRICS_POINTS = 3100
CALIBRATION_POINTS = 4700


def _task(tmp_path):
    """A point of the tiny sweep with a seed and point counts unlike any default (and unlike each other)."""
    text = (write_tiny(tmp_path).read_text()
            .replace("[base]\n", f"[base]\nseed = {SEED}\n", 1)
            .replace("points = 5000\ncalibration_points = 5000",
                     f"points = {METRICS_POINTS}\ncalibration_points = {CALIBRATION_POINTS}", 1))
    path = tmp_path / "args.toml"
    path.write_text(text)
    plan = make_plan(load_spec(path))
    task = next(iter(plan.points.values()))
    assert task.params["seed"] == SEED
    assert (task.metrics_points, task.calibration_points) == (METRICS_POINTS, CALIBRATION_POINTS)
    return task


def test_the_simulation_gets_the_points_seed(tmp_path, monkeypatch):
    task = _task(tmp_path)
    seen = {}

    def simulate_capture(mesh, sensor, poses, out, **kwargs):
        seen.update(kwargs)

    monkeypatch.setattr(point, "simulate_capture", simulate_capture)
    point._simulate(task, tmp_path)
    assert seen["seed"] == SEED


def test_the_reconstruction_gets_the_points_seed_and_metrics_points(tmp_path, monkeypatch):
    task = _task(tmp_path)
    preset = task.presets[0]
    seen = {}

    def reconstruct_capture(capture, out, **kwargs):
        seen.update(kwargs)
        return {}

    monkeypatch.setattr(point, "reconstruct_capture", reconstruct_capture)
    point._reconstruct(task, preset, tmp_path / "capture", tmp_path, "cpu")
    assert seen["seed"] == SEED
    assert seen["overrides"]["metrics_points"] == METRICS_POINTS
    assert {k: v for k, v in seen["overrides"].items() if k != "metrics_points"} == dict(preset.overrides)


def test_the_baselines_get_their_point_counts_and_thresholds_in_their_places(tmp_path, monkeypatch):
    task = _task(tmp_path)
    seen = {}

    def run_baseline(capture, out, method, **kwargs):
        seen.update(kwargs, method=method)
        return {}

    monkeypatch.setattr(point, "run_baseline", run_baseline)
    point._baseline(task, "reprojection", tmp_path / "capture", tmp_path)
    assert seen["method"] == "reprojection"
    assert seen["calibration_points"] == CALIBRATION_POINTS and seen["metrics_points"] == METRICS_POINTS
    assert list(seen["thresholds"]) == list(task.baselines.thresholds) == [5, 20]
    assert seen["resolution"] == task.baselines.resolution


def test_a_dry_run_counts_a_failed_point_among_those_to_run(tmp_path, capsys):
    sweep_file = write_tiny(tmp_path)
    plan = make_plan(load_spec(sweep_file))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    done, failed, _absent = plan.points.values()
    out.write_point(fake_result(done))
    out.write_point(fake_result(failed, failed_methods=("fast",)))
    assert json.loads((out.points / f"{failed.id}.json").read_text())["status"] == "failed"
    assert main(["sweep", str(sweep_file), "--out", str(out.path), "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert f"{failed.id}  failed " in printed and f"{done.id}  done " in printed
    assert printed.rstrip().endswith("3 points, 1 done, 2 to run"), printed
