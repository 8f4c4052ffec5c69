"""How each method's run ended reaches the sweep's records: a preset's `converged` and every method's warnings, a
baseline's threshold at an end of those tried, and a failed point's reason said once, without the temporary work
folder it ran in."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from spadscan.protocol.errors import CaptureError
from spadscan.sweep import point
from spadscan.sweep.plan import make_plan
from spadscan.sweep.point import run_point
from spadscan.sweep.spec import load_spec
from spadscan.sweep.store import SweepDir

from sweep_helpers import write_tiny

OLD_COLUMNS = ["scene", "axis", "value", "point", "status", "reason", "sensor", "schedule", "views", "rings",
               "min_elevation_deg", "max_elevation_deg", "radius_m", "bin_ps", "fov_deg", "power", "ambient", "cycles",
               "albedo", "rays_per_zone", "seed", "bin_mm",
               "fast_status", "fast_chamfer_mm", "fast_accuracy_mm", "fast_completeness_mm", "fast_fscore_5mm",
               "fast_normal_error_deg", "fast_seconds", "fast_steps", "fast_stopped_by",
               "reprojection_status", "reprojection_chamfer_mm", "reprojection_accuracy_mm",
               "reprojection_completeness_mm", "reprojection_fscore_5mm", "reprojection_normal_error_deg",
               "reprojection_seconds", "reprojection_threshold",
               "space_carving_status", "space_carving_chamfer_mm", "space_carving_accuracy_mm",
               "space_carving_completeness_mm", "space_carving_fscore_5mm", "space_carving_normal_error_deg",
               "space_carving_seconds", "space_carving_threshold"]
"""results.csv's columns before the runs' endings were carried: each keeps its name and its order."""
NO_RETURN = "no histogram holds a return above the noise: nothing to reconstruct"


def fake_stages(monkeypatch, *, fast=None, baseline=None):
    """Stand-ins for the simulator, the reconstruction and the baselines: `fast(capture)` and
    `baseline(method, capture)` give a report or raise."""

    def simulate(task, work):
        (work / "capture").mkdir()
        return {"views": task.params["views"]}

    def reconstruct(capture, out, **kwargs):
        return fast(Path(capture))

    def run_baseline(capture, out, method, **kwargs):
        return baseline(method, Path(capture))

    monkeypatch.setattr(point, "_simulate", simulate)
    monkeypatch.setattr(point, "reconstruct_capture", reconstruct)
    monkeypatch.setattr(point, "run_baseline", run_baseline)


def preset_report(capture, converged=False):
    return {"chamfer_mm": 5.2, "steps": 60, "stopped_by": "steps", "seconds": 3.0, "converged": converged,
            "warnings": [] if converged else [
                "the run stopped on its step count well before convergence: its data term was still falling",
                f"{capture}: 27 % of the surface was seen by fewer than 3 views"]}


def baseline_report(method, capture):
    best = 5.0 if method == "reprojection" else 10.0  # reprojection's best is the lowest threshold tried
    return {"chamfer_mm": 22.0, "threshold": best, "floor_z_m": 0.0, "warnings": [],
            "calibration": {"table": [{"threshold": t, "chamfer_mm": 22.0 + abs(t - best)} for t in (5.0, 10.0, 20.0)]}}


@pytest.fixture
def folder(tmp_path):
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    return plan, out


def test_a_run_that_warned_is_recorded_as_such_in_the_point_and_results_csv(folder, monkeypatch):
    plan, out = folder
    fake_stages(monkeypatch, fast=preset_report, baseline=baseline_report)
    task = next(iter(plan.points.values()))
    events = []
    result = run_point(task, str(out.path), emit=lambda event, **fields: events.append((event, fields)))
    assert result["status"] == "done" and result["reason"] is None
    assert events[-1][0] == "done" and events[-1][1]["warnings"] == {"fast": 2}  # log.jsonl's record of the end
    stored = json.loads((out.points / f"{task.id}.json").read_text())
    fast = stored["methods"]["fast"]
    assert fast["converged"] is False and len(fast["warnings"]) == 2
    # The temporary work folder is gone when the point ends: the warning names the point's capture instead.
    assert fast["warnings"][1] == "the point's capture: 27 % of the surface was seen by fewer than 3 views"
    assert stored["methods"]["reprojection"]["warnings"] == []
    assert stored["methods"]["reprojection"]["threshold_edge"] == "lowest"
    assert stored["methods"]["space-carving"]["threshold_edge"] is None

    out.write_results(plan)
    with open(out.path / "results.csv", newline="") as f:
        reader = csv.DictReader(f)
        rows = [r for r in reader if r["point"] == task.id]
        header = reader.fieldnames
    assert header[:len(OLD_COLUMNS)] == OLD_COLUMNS  # the old columns keep their names and places: new ones follow
    row = rows[0]
    assert row["fast_converged"] == "False" and row["fast_warning_count"] == "2"
    assert row["fast_warnings"] == " | ".join(fast["warnings"])
    assert row["reprojection_warning_count"] == "0" and row["reprojection_warnings"] == ""
    assert row["reprojection_threshold_edge"] == "lowest" and row["space_carving_threshold_edge"] == ""
    assert out.endings(plan) == ({task.id: ["fast"]}, {task.id: ["reprojection"]})


def test_a_clean_run_and_a_failed_method_leave_the_ending_cells_plain(folder, monkeypatch):
    plan, out = folder

    def failing(method, capture):
        raise CaptureError(f"{capture}: {method} found no surface")

    fake_stages(monkeypatch, fast=lambda capture: preset_report(capture, converged=True), baseline=failing)
    task = next(iter(plan.points.values()))
    run_point(task, str(out.path))
    out.write_results(plan)
    with open(out.path / "results.csv", newline="") as f:
        row = next(csv.DictReader(f))
    assert row["fast_converged"] == "True" and row["fast_warning_count"] == "0" and row["fast_warnings"] == ""
    assert row["reprojection_warning_count"] == "" and row["reprojection_threshold_edge"] == ""
    assert out.endings(plan) == ({}, {})


def test_every_method_failing_for_one_cause_is_one_short_reason(folder, monkeypatch):
    plan, out = folder

    def no_return(*args):
        raise CaptureError(f"{args[-1]}: {NO_RETURN}")

    fake_stages(monkeypatch, fast=no_return, baseline=no_return)
    task = next(iter(plan.points.values()))
    result = run_point(task, str(out.path))
    assert result["reason"] == f"every method: the point's capture: {NO_RETURN}"
    stored = (out.points / f"{task.id}.json").read_text()
    assert ".running-" not in stored and str(out.work) not in stored


def test_methods_that_fail_for_different_causes_are_grouped_by_cause(folder, monkeypatch):
    plan, out = folder

    def no_return(capture):
        raise CaptureError(f"{capture}: {NO_RETURN}")

    def no_surface(method, capture):
        raise CaptureError("no threshold gave a surface to compare with the ground truth")

    fake_stages(monkeypatch, fast=no_return, baseline=no_surface)
    result = run_point(next(iter(plan.points.values())), str(out.path))
    assert result["reason"] == (f"fast: the point's capture: {NO_RETURN}; reprojection, space-carving: no threshold "
                                f"gave a surface to compare with the ground truth")


@pytest.mark.parametrize("threshold, tried, edge", [
    (5.0, [5.0, 10.0, 20.0], "lowest"), (20.0, [20.0, 5.0, 10.0], "highest"), (10.0, [5.0, 10.0, 20.0], None),
    (7.0, [7.0], "only"), (None, [5.0, 10.0], None), (5.0, [], None)])
def test_a_threshold_at_an_end_of_those_tried_is_flagged(threshold, tried, edge):
    assert point.threshold_edge(threshold, tried) == edge


def test_the_end_of_a_run_counts_the_points_that_warn(tmp_path):
    from spadscan.commands.sweep import finished_lines
    from spadscan.sweep.runner import Summary

    summary = Summary(points=12, earlier=0, ran=12, done=12, rows=14,
                      warned={"a": ["fast"], "b": ["fast", "reprojection"], "c": ["fast"]},
                      edge={"a": ["reprojection"]})
    lines = finished_lines(summary, {}, tmp_path, presets=["fast"])
    assert lines[1] == ("3 of 12 points warn (fast 3, reprojection 1): see results.csv's fast_converged, "
                        "fast_warnings, reprojection_warnings")
    assert lines[2].startswith("1 of 12 points has a baseline's threshold at the edge of the tried thresholds "
                               "(reprojection 1): see results.csv's reprojection_threshold_edge;")
    quiet = finished_lines(Summary(points=2, earlier=0, ran=2, done=2, rows=2), {}, tmp_path, presets=["fast"])
    assert len(quiet) == 2


def test_a_point_whose_sensor_stands_inside_the_object_fails_as_simulate_refuses_it(folder):
    """radius_m = 0.02 around the 0.1 m sphere: the point was simulated, reconstructed and plotted as an ordinary
    result 60 mm off, the simulator's note kept where nothing read it. It fails now, with `simulate`'s reason, and
    no method runs on it."""
    import dataclasses

    plan, out = folder
    task = next(iter(plan.points.values()))
    task = dataclasses.replace(task, params={**task.params, "radius_m": 0.02})
    result = run_point(task, str(out.path))
    assert result["status"] == "failed" and result["methods"] == {}, result
    assert result["reason"].startswith("simulate: 7 of 8 views (0, 1, "), result["reason"]
    assert result["reason"].endswith("put the sensor inside the mesh: no sensor can stand there; move the target or "
                                     "the radius (metres), or the elevations"), result["reason"]
