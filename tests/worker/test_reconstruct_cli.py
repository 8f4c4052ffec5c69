"""`spadscan reconstruct` and `reconstruct_capture`: every file written, the report's contents, one-line errors, result
folders that keep a previous result."""

from __future__ import annotations

import json
import os
import shutil
import time

import numpy as np
import pytest
import torch
import trimesh

from spadscan.cli import main
from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker.outputs import check_out, export_mesh
from spadscan.worker.recon.paper.model import PaperModel
from spadscan.worker.report import folder_view
from spadscan.worker.report.report_html import warnings as page_warnings
from spadscan.worker.report.view3d import VIEW3D

SMALL = ["rays.rays_per_view=32", "rays.importance_rays_per_view=8", "rays.samples_per_ray=24",
         "rays.importance_samples=8", "field.width=48", "field.layers=3", "field.skip_layers=[2]",
         "field.frequencies=4", "mesh_resolution=40", "trace_mesh_resolution=24", "trace_points=2000",
         "metrics_points=5000"]
FILES = {"mesh.ply", "report.json", "preview.png", "error_vs_time.png", "fit.png", "coverage.png"}


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def capture_and_gt(tmp_path_factory):
    import trimesh

    root = tmp_path_factory.mktemp("recon")
    mesh = trimesh.creation.box(extents=(0.07, 0.05, 0.09))
    mesh.apply_translation([0.0, 0.0, 0.045])
    gt = root / "gt.ply"
    mesh.export(gt)
    poses = fibonacci_hemisphere(6, 0.3, target=(0, 0, 0.05), min_elevation_deg=15)
    cap = simulate_capture(mesh, sensor_preset("lcspc-sim"), poses, root / "cap",
                           settings=SimSettings(rays_per_zone=512), progress=False)
    return cap, gt


def small_args():
    return [x for kv in SMALL for x in ("--set", kv)]


@pytest.mark.slow
@pytest.mark.usefixtures("draws_off_screen")  # every file: the pictures of meshes too
def test_two_step_paper_run_writes_every_file(capture_and_gt, tmp_path, capsys):
    cap, gt = capture_and_gt
    out = tmp_path / "out"
    rc = main(["reconstruct", str(cap), "--out", str(out), "--preset", "paper", "--steps", "2", "--gt", str(gt),
               "--device", "cpu", "--seed", "3", "--no-progress", *small_args()])
    assert rc == 0
    assert FILES | {"normals.png"} <= {p.name for p in out.iterdir()}
    for name in FILES - {"report.json", "mesh.ply"} | {"normals.png"}:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = json.loads((out / "report.json").read_text())
    assert report["preset"] == "paper" and report["device"] == "cpu" and report["steps"] == 2
    assert report["seed"] == 3 and report["stopped_by"] == "steps" and report["seconds"] > 0
    assert report["capture"] == str(cap.resolve())
    summary = capsys.readouterr().out
    # The metrics' points come from their own fixed seed, not the run's: `spadscan eval` of the mesh says the same.
    assert report["metrics_seed"] == 0
    assert main(["eval", str(out / "mesh.ply"), "--gt", str(gt), "--points", str(report["n_points"]), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["chamfer_mm"] == pytest.approx(report["chamfer_mm"], abs=1e-5)
    assert set(report["terms"]) == {"pileup", "crosstalk", "table", "tv", "reference_pulse"}
    assert report["terms"]["pileup"] and not report["terms"]["crosstalk"] and not report["terms"]["table"]
    assert np.isfinite(report["final_loss"])
    assert report["config"]["rays"]["samples_per_ray"] == 24  # the resolved config, overrides included
    for key in ("chamfer_mm", "accuracy_mm", "completeness_mm", "fscore_5mm", "normal_error_deg"):
        assert np.isfinite(report[key])
    trace = report["trace"]
    assert [p["step"] for p in trace] == [0, 1, 2]
    assert all(np.isfinite(p["chamfer_mm"]) for p in trace) and "excluded" in report["trace_note"]
    assert trace[0]["seconds"] == 0 and trace[-1]["seconds"] == pytest.approx(report["seconds"], abs=1e-3)
    assert set(report["files"]) >= FILES | {"report.html"}
    page = (out / "report.html").read_text()
    assert f"{report['chamfer_mm']:.4g} mm" in page and "paper" in page
    for name in ("preview.png", "error_vs_time.png", "fit.png", "normals.png", "coverage.png"):
        assert f'src="{name}"' in page
    header = (out / "mesh.ply").read_bytes()[:1000]
    assert b"property float nx" in header or b"property double nx" in header  # per-vertex normals are stored
    assert "paper: 2 steps" in summary and "Chamfer" in summary
    assert "(open this first), " + ", ".join(sorted(set(report["files"]) - {"report.html"})) in summary
    # The final figure says how it was scored: the checkpoints' (the trace, the bar) are coarser.
    assert report["chamfer_scoring"] == "final 40-cell mesh, 5,000 points"
    assert f"Chamfer {report['chamfer_mm']:.2f} mm (final 40-cell mesh, 5,000 points;" in summary
    assert "2000 points per mesh on a 24-cell marching-cubes grid" in report["trace_note"]
    # Both clocks: training (what --budget-s bounds) and the whole run (set-up, mesh and metrics too).
    assert f"in {report['seconds']:.1f} s of training ({report['wall_seconds']:.1f} s in all)" in summary


class SlowToEvaluate:
    """A stand-in model whose steps take about 10 ms; the evaluation below takes 300 ms."""

    def step(self) -> dict:
        import time

        time.sleep(0.01)
        return {"loss": 1.0}


def test_checkpoint_evaluation_counts_against_the_time_budget():
    import time

    from spadscan.worker.recon.model_api import RunPlan
    from spadscan.worker.recon.trainer import train

    evaluated = []

    def evaluate():
        time.sleep(0.3)
        evaluated.append(1)
        return {"chamfer_mm": 1.0}

    result = train(SlowToEvaluate(), RunPlan(steps=10**6, budget_s=1.5, seed=0), checkpoints=12, evaluate=evaluate,
                   progress=False)
    assert result.stopped_by == "budget"
    assert result.seconds < 1.5, "evaluation time was charged to the budget, so training got less than all of it"
    assert result.eval_seconds >= 0.3 * len(evaluated) and len(evaluated) >= 2
    assert result.seconds + result.eval_seconds < 1.5 + 0.3 + 0.3 + 5.0  # one step and one evaluation past, at most
    skipped = [p for p in result.trace if "skipped" in p.get("note", "")]
    assert len(evaluated) + len(skipped) == len(result.trace)


class SlowStep:
    """A stand-in model whose one step outlasts half the budget below."""

    def step(self) -> dict:
        import time

        time.sleep(0.6)
        return {"loss": 1.0}


def test_a_run_that_ends_on_a_skipped_checkpoint_still_evaluates_its_end():
    import time

    from spadscan.worker.recon.model_api import RunPlan
    from spadscan.worker.recon.trainer import train

    def evaluate():
        time.sleep(0.5)
        return {"chamfer_mm": 1.0}

    # Start: evaluated (0.5 s). One step (0.6 s) reaches the mid-run mark, whose evaluation would overrun the 1 s
    # budget and is skipped; the budget is then spent, so the run ends on that very checkpoint.
    result = train(SlowStep(), RunPlan(steps=10**6, budget_s=1.0, seed=0), checkpoints=2, evaluate=evaluate,
                   progress=False)
    assert result.stopped_by == "budget"
    assert result.trace[-1]["step"] == result.steps
    assert result.trace[-1].get("chamfer_mm") == 1.0, result.trace


class ConvergesAt:
    """A stand-in model that reports `converged` from step `at` on."""

    def __init__(self, at: int):
        self.at, self.steps = at, 0

    def step(self) -> dict:
        self.steps += 1
        return {"loss": 1.0 / self.steps, "converged": self.steps >= self.at}


@pytest.mark.parametrize("early_stop, steps, stopped_by", [(True, 7, "converged"), (False, 20, "steps")])
def test_early_stop_ends_the_run_at_the_first_converged_step(early_stop, steps, stopped_by):
    from spadscan.worker.recon.model_api import RunPlan
    from spadscan.worker.recon.trainer import train

    result = train(ConvergesAt(7), RunPlan(steps=20, budget_s=None, seed=0), checkpoints=4,
                   evaluate=lambda: {"chamfer_mm": 1.0}, progress=False, early_stop=early_stop)
    assert (result.steps, result.stopped_by) == (steps, stopped_by)
    assert result.trace[-1]["step"] == steps and result.trace[-1]["chamfer_mm"] == 1.0  # the end is evaluated


def test_the_progress_bar_labels_its_chamfer_as_the_checkpoints(capsys):
    from spadscan.worker.job_progress import parse_progress
    from spadscan.worker.recon.model_api import RunPlan
    from spadscan.worker.recon.trainer import train
    from spadscan.worker.reconstruct import checkpoint_scoring
    from spadscan.worker.recon.presets import preset_config

    note = f"checkpoint {checkpoint_scoring(preset_config('fast'), short=True)}"
    assert note == "checkpoint 128-cell mesh; 30k points"
    train(ConvergesAt(100), RunPlan(steps=4, budget_s=None, seed=0), checkpoints=2,
          evaluate=lambda: {"chamfer_mm": 1.4321}, progress=True, score_note=note)
    err = capsys.readouterr().err
    assert "chamfer=1.43mm, scored=at step 4; checkpoint 128-cell mesh; 30k points" in err
    # The lab dashboard and the demo read the bar from a job's log: they still find the Chamfer, and show the label.
    progress = parse_progress(err)
    assert progress.chamfer_mm == 1.43 and progress.chamfer_step == 4
    assert "scored at step 4; checkpoint 128-cell mesh; 30k points" in progress.line()


def test_a_chamfer_whose_later_checkpoints_went_unscored_says_how_old_it_is(capsys):
    """Under a short budget the checkpoints' scoring share is spent early: the bar then keeps the last scored
    Chamfer for the rest of the run, and says the step it belongs to rather than look like the fit is stuck."""
    from spadscan.worker.job_progress import parse_progress
    from spadscan.worker.recon.model_api import RunPlan
    from spadscan.worker.recon.trainer import train

    scores = iter([{}, {"chamfer_mm": 25.67}])  # the start's checkpoint, the first in the run; the rest unscored
    train(ConvergesAt(100), RunPlan(steps=8, budget_s=None, seed=0), checkpoints=4,
          evaluate=lambda: next(scores, {}), progress=True)
    progress = parse_progress(capsys.readouterr().err)
    assert progress.fields["step"] == "8"
    assert (progress.chamfer_mm, progress.chamfer_step) == (25.67, 2), progress.fields
    assert "Chamfer 25.67 mm, scored at step 2" in progress.line()


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("spadscan: error: "), err
    return err[0]


def test_bad_capture_is_a_one_line_error(tmp_path, capsys):
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "scan.json").write_text("{not json")
    assert main(["reconstruct", str(tmp_path / "junk"), "--out", str(tmp_path / "o"), "--preset", "paper"]) == 1
    assert "scan.json" in one_line_error(capsys)
    assert main(["reconstruct", str(tmp_path / "nothing"), "--out", str(tmp_path / "o"), "--preset", "paper"]) == 1
    assert "no such capture" in one_line_error(capsys)


def test_bad_arguments_are_one_line_errors(capture_and_gt, tmp_path, capsys):
    cap, _ = capture_and_gt
    base = ["reconstruct", str(cap), "--out", str(tmp_path / "o"), "--preset", "paper", "--no-progress"]
    assert main(base + ["--gt", str(tmp_path / "missing.obj")]) == 1
    assert "missing.obj" in one_line_error(capsys)
    assert main(base + ["--steps", "0"]) == 1
    assert "steps" in one_line_error(capsys)
    assert main(base + ["--steps", str(10**20)]) == 1  # a slip of the keyboard, not weeks of training
    assert "steps 100000000000000000000 must be an integer in [1, 10,000,000]" in one_line_error(capsys)
    assert main(base + ["--budget-s", "1e9"]) == 1
    assert "time budget 1000000000.0 s must be a number of seconds > 0 and at most 604800 (a week)" in \
        one_line_error(capsys)
    for preset in (base, ["reconstruct", str(cap), "--out", str(tmp_path / "o"), "--no-progress"]):
        assert main(preset + ["--seed", "99999999999999999999", "--steps", "1"]) == 1  # past torch's generators
        assert f"seed 99999999999999999999 must be an integer in [0, {2**63 - 1}]" in one_line_error(capsys)
    assert main(base + ["--set", "rays.no_such_field=1"]) == 1
    assert "no_such_field" in one_line_error(capsys)
    assert main(base + ["--set", "rays.samples_per_ray=-1"]) == 1
    assert "rays.samples_per_ray -1 must be an integer >= 2" in one_line_error(capsys)  # its own range
    assert main(base + ["--set", "loss.tv_weight=1e999"]) == 1
    assert "finite" in one_line_error(capsys)
    fast = ["reconstruct", str(cap), "--out", str(tmp_path / "o"), "--no-progress"]
    assert main(fast + ["--set", "rays.samples_per_ray=64"]) == 1  # the fast preset would ignore it
    assert "preset 'fast' has no section 'rays'" in one_line_error(capsys)
    assert main(fast + ["--set", "schedule.grad_blur_passes=0"]) == 1  # a key of earlier versions
    assert "parts.blur.passes (parts.blur.enabled=false: off)" in one_line_error(capsys)
    assert main(fast + ["--set", "parts.empty_space.heard_views=0"]) == 1
    assert "parts.empty_space.heard_views 0" in one_line_error(capsys)
    assert main(fast + ["--set", "parts.empty_space.heard_threshold=0"]) == 1
    assert "parts.empty_space.heard_threshold 0.0 must be > 0" in one_line_error(capsys)
    assert not (tmp_path / "o").exists()  # a refused config writes nothing
    if not torch.cuda.is_available():
        assert main(base + ["--device", "cuda", "--steps", "1"]) == 1
        assert "CUDA" in one_line_error(capsys)


def test_help_names_every_option(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["reconstruct", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for flag in ("--out", "--preset", "--budget-s", "--steps", "--gt", "--device", "--seed"):
        assert flag in text
    from dataclasses import fields

    from spadscan.worker.recon.fast.parts import FastPartsConfig

    listed = " ".join(text.split())
    missing = [f.name for f in fields(FastPartsConfig) if f.name not in listed]
    assert not missing, f"the help's list of the fast preset's parts leaves out {missing}"


# ---- result folders: a previous result is kept unless --overwrite, a failed write leaves the previous mesh, an
# unfinished capture is reconstructed with a warning, and the stages after training say what they do.

def _recon(cap, out, *extra):
    return main(["reconstruct", str(cap), "--out", str(out), "--preset", "paper", "--steps", "1", "--device", "cpu",
                 "--no-progress", *small_args(), *extra])


def _error_lines(capsys):
    return [line for line in capsys.readouterr().err.splitlines() if line.startswith("spadscan: error:")]


def test_a_previous_result_is_kept_unless_overwrite(capture_and_gt, tmp_path, capsys):
    cap, _ = capture_and_gt
    out = tmp_path / "out"
    out.mkdir()
    (out / "mesh.ply").write_text("the previous mesh")
    assert _recon(cap, out) == 1
    err = _error_lines(capsys)
    assert len(err) == 1 and "already holds a result" in err[0] and "--overwrite" in err[0]
    assert (out / "mesh.ply").read_text() == "the previous mesh"
    assert _recon(cap, out, "--overwrite", "--threads", "1") == 0
    assert len(trimesh.load(out / "mesh.ply").vertices) > 0
    assert json.loads((out / "report.json").read_text())["torch_threads"] == 1


def test_an_overwritten_result_leaves_none_of_its_own_files_and_lists_only_this_runs(capture_and_gt, tmp_path,
                                                                                      capsys):
    cap, _ = capture_and_gt
    out = tmp_path / "out"
    out.mkdir()
    previous = ["mesh.ply", "normals.png", "report.html", "report.json"]
    for name in previous[:-1]:
        (out / name).write_text(f"the previous {name}")
    (out / "report.json").write_text(json.dumps({"files": previous}))
    (out / "notes.txt").write_text("the user's own notes")
    an_hour_ago = time.time() - 3600  # the previous run's time
    for path in out.iterdir():
        os.utime(path, (an_hour_ago, an_hour_ago))
    assert _recon(cap, out, "--overwrite", "--no-gt") == 0
    report = json.loads((out / "report.json").read_text())
    assert not (out / "normals.png").exists(), "the replaced run's normals picture does not stand beside this one"
    assert (out / "notes.txt").read_text() == "the user's own notes"
    assert "notes.txt" not in report["files"] and "normals.png" not in report["files"]
    assert {"mesh.ply", "report.json", "report.html"} <= set(report["files"])
    assert set(report["files"]) <= {p.name for p in out.iterdir()}
    page = (out / "report.html").read_text()
    assert "notes.txt" not in page and 'href="normals.png"' not in page
    assert "removed the replaced result's normals.png" in capsys.readouterr().err


@pytest.mark.usefixtures("draws_off_screen")  # the 3D view
def test_a_result_lists_its_3d_view_and_one_not_made_again_is_not_left_standing(capture_and_gt, tmp_path,
                                                                                 monkeypatch):
    """view3d.html is the run's file like its pictures: listed in report.json, and a run over it with --overwrite
    that cannot make its own removes it (the replaced run's view stood under the new report)."""
    cap, _ = capture_and_gt
    out = tmp_path / "out"
    assert _recon(cap, out, "--no-gt") == 0
    report = json.loads((out / "report.json").read_text())
    assert VIEW3D in report["files"]
    report["files"].remove(VIEW3D)  # as earlier versions listed their files: the view is the result's all the same
    (out / "report.json").write_text(json.dumps(report))
    an_hour_ago = time.time() - 3600
    for path in out.iterdir():
        os.utime(path, (an_hour_ago, an_hour_ago))

    def cannot(*args, **kwargs):
        raise SpadscanError("no scene for the 3D view")

    monkeypatch.setattr(folder_view, "write_view3d", cannot)
    assert _recon(cap, out, "--overwrite", "--no-gt") == 0
    assert not (out / VIEW3D).exists()
    assert VIEW3D not in json.loads((out / "report.json").read_text())["files"]
    assert f"no 3D view ({VIEW3D} was not written)" in (out / "report.html").read_text()


def test_a_deterministic_render_is_rendered_once_for_the_fit_check(capture_and_gt, tmp_path, monkeypatch):
    """The paper preset's render has no random part: its fit check rendered every view four times over (three of
    them the first again: at the preset's sizes a quarter of an hour of a 16-view capture's end)."""
    calls = []
    render = PaperModel.render_histograms

    def counted(model, view_ids):
        calls.append(list(view_ids))
        return render(model, view_ids)

    monkeypatch.setattr(PaperModel, "render_histograms", counted)
    cap, _ = capture_and_gt
    assert _recon(cap, tmp_path / "out", "--no-gt") == 0
    assert calls == [[0, 1, 2, 3, 4, 5]]  # the capture's six views, once


def test_a_scene_box_that_loses_the_object_says_so_not_that_nothing_returned(capture_and_gt, tmp_path, capsys):
    """A scene radius of 50 m makes a hull cell 2 m across: carving keeps nothing, and the run said no histogram
    showed a return, which every one of them did."""
    cap, _ = capture_and_gt
    wide = tmp_path / "wide"
    shutil.copytree(cap, wide)
    manifest = json.loads((wide / "scan.json").read_text())
    manifest["scene"] = {**manifest.get("scene", {}), "center": [0.0, 0.0, 0.05], "radius": 50.0}
    (wide / "scan.json").write_text(json.dumps(manifest))
    assert main(["reconstruct", str(wide), "--out", str(tmp_path / "o"), "--steps", "1", "--no-progress"]) == 1
    err = _error_lines(capsys)
    assert len(err) == 1 and "although 6 histograms show a return" in err[0] and "scene.radius" in err[0], err


def test_a_file_in_the_way_and_bad_threads_are_one_line_errors(capture_and_gt, tmp_path, capsys):
    cap, _ = capture_and_gt
    (tmp_path / "afile").write_text("x")
    assert _recon(cap, tmp_path / "afile") == 1
    assert "is not a folder" in _error_lines(capsys)[0]
    assert _recon(cap, tmp_path / "o", "--threads", "0") == 1
    assert "threads 0" in _error_lines(capsys)[0]


def test_a_bad_capture_leaves_no_folder_behind(tmp_path, capsys):
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "scan.json").write_text("{not json")
    assert _recon(tmp_path / "junk", tmp_path / "o") == 1
    assert not (tmp_path / "o").exists()


def test_a_capture_whose_histograms_hold_no_return_is_refused_not_fitted(tmp_path, capsys):
    """Background alone in every histogram (here every return arrives before the first bin: a wrong range offset):
    both presets refuse in one line, as the baselines do, rather than shape a mesh out of noise."""
    from spadscan.protocol.scenes import builtin_scene
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import simulate_capture

    sensor = sensor_preset("lcspc-sim").with_(zero_bin=-1000.0)
    simulate_capture(builtin_scene("sphere"), sensor, fibonacci_hemisphere(8, 0.5, (0, 0, 0.1)), tmp_path / "dark",
                     scene={"builtin": "sphere"}, progress=False)
    for preset in ("fast", "paper"):
        assert main(["reconstruct", str(tmp_path / "dark"), "--out", str(tmp_path / preset), "--preset", preset,
                     "--steps", "5", "--no-gt", "--no-progress"]) == 1
        (line,) = _error_lines(capsys)
        assert "no histogram holds a return above the noise" in line and "nothing to reconstruct" in line
        assert not (tmp_path / preset).exists()


@pytest.mark.parametrize("sensor_change", [{"signal_scale": 0.0}, {"gain": 1e-300}], ids=["no-scale", "no-gain"])
def test_a_sensor_model_that_predicts_no_signal_is_refused(capture_and_gt, tmp_path, capsys, sensor_change):
    """A sensor record whose signal_scale is 0 (or whose zones' gains vanish in float32): every render is
    background, and the run used to end with the carved hull, exit status 0 and only a generic misfit warning."""
    cap, _ = capture_and_gt
    broken = tmp_path / "silent-model"
    shutil.copytree(cap, broken)
    manifest = json.loads((broken / "scan.json").read_text())
    if "gain" in sensor_change:
        for zone in manifest["sensor"]["zones"]:
            zone["gain"] = sensor_change["gain"]
    else:
        manifest["sensor"].update(sensor_change)
    (broken / "scan.json").write_text(json.dumps(manifest))
    assert _recon(broken, tmp_path / "o", "--steps", "5") == 1
    (line,) = _error_lines(capsys)
    assert "the capture's sensor model predicts no signal" in line and not (tmp_path / "o").exists(), line


def test_a_surface_touching_the_sensor_is_said_to_be_the_reason_there_is_no_return(tmp_path, capsys):
    """Every view 1 mm from a ball's surface: all the photons land in the first bin, where no peak can stand out of
    its own background. The refusal says what that means rather than "the object out of range"."""
    from spadscan.protocol.schedules import look_at
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import simulate_capture

    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    directions = [(1, 0, 0.3), (-1, 0, 0.3), (0, 1, 0.3), (0, -1, 0.3), (0.6, 0.6, 0.6), (-0.6, -0.6, 0.6)]
    poses = np.stack([look_at(0.101 * np.asarray(d) / np.linalg.norm(d), (0, 0, 0)) for d in directions])
    simulate_capture(ball, sensor_preset("lcspc-sim"), poses, tmp_path / "touching", progress=False)
    assert main(["reconstruct", str(tmp_path / "touching"), "--out", str(tmp_path / "o"), "--steps", "5", "--no-gt",
                 "--no-progress"]) == 1
    (line,) = _error_lines(capsys)
    assert "no histogram holds a return above the noise" in line and "a surface touching the sensor" in line, line
    assert "out of range" not in line and not (tmp_path / "o").exists()


@pytest.mark.parametrize("ambient", [2.5e-4, 0.05])
def test_ambient_light_alone_is_not_said_to_be_a_surface_touching_the_sensor(tmp_path, capsys, ambient):
    """Every view looks away from the ball, under ambient light: a first-photon sensor's counts of it fall bin by
    bin (fewer cycles are still live), so their highest bin is the first, which the refusal read as photons piling
    up 2 mm from the sensor. Read through pile-up the rates are flat: the refusal gives the general causes."""
    from spadscan.protocol.scenes import builtin_scene
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    simulate_capture(builtin_scene("sphere"), sensor_preset("lcspc-sim"), fibonacci_hemisphere(8, 0.5, (3, 3, 0.1)),
                     tmp_path / "away", settings=SimSettings(ambient=ambient), progress=False)
    assert main(["reconstruct", str(tmp_path / "away"), "--out", str(tmp_path / "o"), "--steps", "5", "--no-gt",
                 "--no-progress"]) == 1
    (line,) = _error_lines(capsys)
    assert "no histogram holds a return above the noise" in line and "out of range or out of every view" in line
    assert "touching" not in line, line


def test_an_unfinished_capture_is_reconstructed_with_a_warning(capture_and_gt, tmp_path, capsys):
    import shutil

    cap, gt = capture_and_gt
    running = tmp_path / "running"
    shutil.copytree(cap, running)
    manifest = json.loads((running / "scan.json").read_text())
    manifest["state"] = "running"
    (running / "scan.json").write_text(json.dumps(manifest))
    assert _recon(running, tmp_path / "o", "--gt", str(gt)) == 0
    err = capsys.readouterr().err
    assert err.count("the capture is running, not complete") == 1, "said once, when the capture was loaded"
    # The stages after training say what they do (they can take minutes on a large mesh).
    for stage in ("extracting the mesh", "metrics against the ground truth", "pictures and report"):
        assert stage in err
    # The pictures first: their time is kept back at a loaded machine's figure, and what they leave over on an idle
    # one goes to the metric points.
    assert err.index("extracting the mesh") < err.index("pictures and report") < err.index("metrics against")
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["capture_state"] == "running" and "not complete" in report["capture_note"]
    assert report["capture_note"] in report["warnings"]  # scripts read the warnings, not every field
    assert page_warnings(report).count(report["capture_note"]) == 1  # once at the top of the page
    out = tmp_path / "b"
    assert main(["baseline", "space-carving", str(running), "--out", str(out), "--resolution", "16",
                 "--gt", "builtin:sphere", "--points", "5000"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["capture_state"] == "running" and "chamfer_mm" in report  # builtin: ground truths work too
    assert main(["baseline", "space-carving", str(running), "--out", str(out), "--resolution", "16"]) == 1
    assert "already holds a result" in _error_lines(capsys)[0]


@pytest.mark.slow
def test_a_ground_truth_on_a_table_is_scored_above_it(capture_and_gt, tmp_path, capsys):
    import trimesh

    cap, gt = capture_and_gt
    slab = trimesh.creation.box([2.0, 2.0, 0.05]).apply_translation([0, 0, -0.025])  # its top: z = 0
    on_table = tmp_path / "on_table.ply"
    trimesh.util.concatenate([trimesh.load(gt), slab]).export(on_table)
    assert _recon(cap, tmp_path / "r", "--gt", str(on_table)) == 0
    assert "scoring the object above z = 0.0050 m" in capsys.readouterr().err
    assert main(["baseline", "space-carving", str(cap), "--out", str(tmp_path / "b"), "--resolution", "16",
                 "--gt", str(on_table), "--points", "5000"]) == 0
    for out in ("r", "b"):
        report = json.loads((tmp_path / out / "report.json").read_text())
        assert report["ground_truth_cut_above_z_m"] == pytest.approx(0.005)
        assert "table top + 5 mm" in report["ground_truth_scored"]
        assert report["completeness_mm"] < 100, "scored whole, the 2 m slab would put it over a metre"
    assert "table top + 5 mm" in (tmp_path / "r" / "report.html").read_text()
    assert _recon(cap, tmp_path / "w", "--gt", str(gt)) == 0
    whole = json.loads((tmp_path / "w" / "report.json").read_text())
    assert whole["ground_truth_cut_above_z_m"] is None and "ground_truth_scored" not in whole


def test_a_failed_mesh_write_leaves_the_previous_file(tmp_path):
    path = tmp_path / "mesh.ply"
    export_mesh(trimesh.creation.box(), path)
    before = path.read_bytes()

    class FullDisk(trimesh.Trimesh):
        def export(self, file_obj=None, **kw):
            with open(file_obj, "wb") as f:
                f.write(b"ply\n half a mesh")
            raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        export_mesh(FullDisk(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]]), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["mesh.ply"], "no temporary file left"


def test_check_out(tmp_path):
    assert check_out(tmp_path / "new", False) == tmp_path / "new"
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "report.json").write_text("{}")
    assert check_out(tmp_path / "r", True) == tmp_path / "r"
    (tmp_path / "r" / "notes.txt").write_text("an unrelated file does not make a result")
    (tmp_path / "r" / "report.json").unlink()
    assert check_out(tmp_path / "r", False) == tmp_path / "r"


def _naming(cap, dest, scene: dict):
    """A copy of capture `cap` at `dest` whose manifest's scene record holds `scene` (as simulate and import-lcspc
    write it)."""
    import shutil

    shutil.copytree(cap, dest)
    manifest = json.loads((dest / "scan.json").read_text())
    manifest["scene"] = {**manifest.get("scene", {}), **scene}
    (dest / "scan.json").write_text(json.dumps(manifest))
    return dest


def test_the_ground_truth_a_capture_names_is_used_unless_no_gt(capture_and_gt, tmp_path, capsys):
    cap, gt = capture_and_gt
    named = _naming(cap, tmp_path / "named", {"mesh": str(gt)})
    assert _recon(named, tmp_path / "r") == 0
    assert f"ground truth: {gt}, named by the capture" in capsys.readouterr().err
    report = json.loads((tmp_path / "r" / "report.json").read_text())
    assert np.isfinite(report["chamfer_mm"]) and report["ground_truth"] == str(gt)
    assert _recon(named, tmp_path / "n", "--no-gt") == 0
    assert "ground truth" not in capsys.readouterr().err
    report = json.loads((tmp_path / "n" / "report.json").read_text())
    assert "chamfer_mm" not in report
    assert main(["baseline", "space-carving", str(named), "--out", str(tmp_path / "b"), "--resolution", "16",
                 "--points", "5000"]) == 0
    assert "named by the capture" in capsys.readouterr().err
    assert "chamfer_mm" in json.loads((tmp_path / "b" / "report.json").read_text())


@pytest.mark.usefixtures("draws_off_screen")  # normals.png; the test above runs where nothing can be drawn
def test_the_normals_picture_is_drawn_against_the_ground_truth_a_capture_names_and_not_with_no_gt(capture_and_gt,
                                                                                                   tmp_path):
    cap, gt = capture_and_gt
    named = _naming(cap, tmp_path / "named", {"mesh": str(gt)})
    assert _recon(named, tmp_path / "r") == 0
    assert (tmp_path / "r" / "normals.png").exists()
    assert _recon(named, tmp_path / "n", "--no-gt") == 0
    assert not (tmp_path / "n" / "normals.png").exists()


def test_a_named_ground_truth_that_cannot_be_used_is_said_and_the_run_goes_on(capture_and_gt, tmp_path, capsys):
    cap, _ = capture_and_gt
    gone = tmp_path / "gone.ply"
    named = _naming(cap, tmp_path / "named", {"ground_truth": str(gone)})
    assert _recon(named, tmp_path / "r") == 0
    assert f"ground truth: {gone}: no such ground-truth mesh; no metrics" in capsys.readouterr().err
    report = json.loads((tmp_path / "r" / "report.json").read_text())
    assert "chamfer_mm" not in report
    # The report says why it has no metrics, as a worker's job's does: the terminal's line scrolls away.
    assert report["ground_truth_note"] == f"{gone}: no such ground-truth mesh; no metrics"
    assert "the named ground truth was not used" in (tmp_path / "r" / "report.html").read_text()
    assert main(["baseline", "space-carving", str(named), "--out", str(tmp_path / "s"), "--resolution", "16"]) == 0
    assert json.loads((tmp_path / "s" / "report.json").read_text())["ground_truth_note"].endswith("no metrics")
    assert "the named ground truth was not used" in (tmp_path / "s" / "report.html").read_text()
    # --calibrate needs a ground truth; the one the capture names serves, and a missing one is the same error.
    assert main(["baseline", "reprojection", str(named), "--out", str(tmp_path / "b"), "--calibrate"]) == 1
    assert "--calibrate needs a ground truth" in _error_lines(capsys)[0]


def test_gt_and_no_gt_exclude_each_other(capture_and_gt, tmp_path, capsys):
    cap, gt = capture_and_gt
    with pytest.raises(SystemExit):
        main(["reconstruct", str(cap), "--out", str(tmp_path / "o"), "--gt", str(gt), "--no-gt"])
    assert "not allowed with argument" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_results_are_never_written_among_a_captures_measurements(capture_and_gt, tmp_path, capsys):
    cap, _ = capture_and_gt
    for out in (cap, cap / "chunk-000000", cap / "results"):
        assert _recon(cap, out) == 1
        assert f"--out {out} lies inside the capture {cap}" in _error_lines(capsys)[0]
        assert main(["baseline", "reprojection", str(cap), "--out", str(out), "--no-gt"]) == 1
        assert "lies inside the capture" in _error_lines(capsys)[0]
    assert not (cap / "results").exists() and not (cap / "mesh.ply").exists()
    check_out(cap / "recon" / "by-hand", False, capture=cap)  # where the worker puts its results: allowed


def test_results_are_never_written_among_another_captures_measurements(capture_and_gt, tmp_path, capsys):
    """--out in a copy of the capture, or in a chunk of it: the check compared --out with the capture read only,
    and mesh.ply, report.json and the pictures landed among the other capture's chunks, exit status 0. Its recon/
    folder stays allowed, as the capture's own is."""
    import shutil

    cap, _ = capture_and_gt
    other = tmp_path / "copy"
    shutil.copytree(cap, other)
    before = sorted(p.name for p in other.rglob("*"))
    for out in (other, other / "chunk-000000", other / "results"):
        assert _recon(cap, out) == 1
        assert f"--out {out} lies inside the capture {other}: results there" in _error_lines(capsys)[0]
        assert main(["baseline", "reprojection", str(cap), "--out", str(out), "--no-gt"]) == 1
        assert f"lies inside the capture {other}" in _error_lines(capsys)[0]
    assert sorted(p.name for p in other.rglob("*")) == before
    check_out(other / "recon" / "by-hand", False, capture=cap)


@pytest.mark.parametrize("command", ["simulate", "import-lcspc"])
def test_a_new_capture_is_never_made_inside_another(capture_and_gt, tmp_path, capsys, command):
    cap, _ = capture_and_gt
    out = cap / "recon" / "new"
    argv = (["simulate", "builtin:sphere", "--views", "4", "--no-progress"] if command == "simulate" else
            ["import-lcspc", str(tmp_path / "scene.json"), "--no-progress"])
    assert main([*argv, "--out", str(out)]) == 1
    assert _error_lines(capsys)[0] == (f"spadscan: error: --out {out} lies inside the capture {cap.resolve()}: a "
                                       f"capture there would be mixed into its measurements; choose a folder "
                                       f"outside it")
    assert not out.exists()


def test_more_threads_than_cores_is_a_warning(capture_and_gt, tmp_path, capsys, monkeypatch):
    import spadscan.worker.reconstruct as reconstruct

    cap, _ = capture_and_gt
    monkeypatch.setattr(reconstruct, "machine_cores", lambda: 1)
    assert _recon(cap, tmp_path / "o", "--threads", "2") == 0
    assert "warning: 2 CPU threads on 1 cores" in capsys.readouterr().err
    monkeypatch.setattr(reconstruct, "machine_cores", lambda: 2)
    assert _recon(cap, tmp_path / "p", "--threads", "2") == 0
    assert "CPU threads on" not in capsys.readouterr().err


def test_a_default_run_of_days_on_a_cpu_is_a_warning(capture_and_gt, tmp_path, capsys, monkeypatch):
    import dataclasses

    import spadscan.worker.reconstruct as reconstruct

    cap, _ = capture_and_gt
    # The paper preset's 300,000 default steps, made one so that the run ends at once; the warning's bar made one too.
    monkeypatch.setattr(reconstruct, "LONG_CPU_STEPS", 1)
    real = reconstruct.preset_config
    monkeypatch.setattr(reconstruct, "preset_config", lambda name: dataclasses.replace(real(name), default_steps=1))
    base = ["reconstruct", str(cap), "--preset", "paper", "--device", "cpu", "--no-progress", *small_args()]
    assert main([*base, "--out", str(tmp_path / "p")]) == 0
    assert "warning: preset 'paper' runs 1 steps by default: days on a CPU" in capsys.readouterr().err
    assert main([*base, "--out", str(tmp_path / "s"), "--steps", "1"]) == 0
    assert "by default" not in capsys.readouterr().err


def _previous_result(out):
    """A previous run's result in `out` (an hour old), and the user's own notes beside it."""
    out.mkdir()
    files = {"mesh.ply": "the previous mesh", "report.html": "the previous page",
             "report.json": json.dumps({"files": ["mesh.ply", "report.html", "report.json"]})}
    for name, text in files.items():
        (out / name).write_text(text)
    (out / "notes.txt").write_text("the user's own notes")
    an_hour_ago = time.time() - 3600
    for path in out.iterdir():
        os.utime(path, (an_hour_ago, an_hour_ago))
    return {**files, "notes.txt": "the user's own notes"}


def _folder(out):
    return ({p.name: p.read_bytes().decode(errors="replace") for p in out.iterdir() if p.is_file()},
            sorted(p.name for p in out.iterdir() if p.is_dir()))


def test_an_overwrite_interrupted_after_its_mesh_leaves_the_previous_result_whole(capture_and_gt, tmp_path):
    """Ctrl-C once the new mesh is written (during the pictures and report): the folder holds the previous result
    as it was, not the new mesh under the old report."""
    from spadscan.worker.recon.config import parse_override
    from spadscan.worker.reconstruct import reconstruct_capture

    cap, gt = capture_and_gt
    out = tmp_path / "out"
    before = _previous_result(out)

    def interrupt_at_the_pictures(line):
        if line.startswith("pictures and report"):
            assert (out / "mesh.ply").read_text(errors="replace") != "the previous mesh"  # the new one is written
            raise KeyboardInterrupt

    overrides = dict(parse_override(text) for text in SMALL)
    with pytest.raises(KeyboardInterrupt):
        reconstruct_capture(cap, out, preset="paper", steps=1, gt=gt, device="cpu", progress=False,
                            overrides=overrides, log=interrupt_at_the_pictures)
    assert _folder(out) == (before, [])


def test_a_result_left_aside_by_a_killed_run_counts_as_a_result_and_comes_back(capture_and_gt, tmp_path, capsys):
    """A run killed (SIGKILL) while replacing a result leaves it in out/.replaced/: the folder still holds a result
    (no run replaces it without --overwrite), and the next run puts it back before it sets it aside again."""
    cap, _ = capture_and_gt
    out = tmp_path / "out"
    before = _previous_result(out)
    (out / ".replaced").mkdir()
    for name in ("mesh.ply", "report.html", "report.json"):
        (out / name).rename(out / ".replaced" / name)
    (out / "mesh.ply").write_text("half of a new mesh")
    assert _recon(cap, out) == 1
    assert "already holds a result" in _error_lines(capsys)[0]
    assert _recon(cap, out, "--overwrite", "--no-gt") == 0
    assert "put back the previous result that a run stopped mid-way had set aside" in capsys.readouterr().err
    files, folders = _folder(out)
    assert folders == [] and files["notes.txt"] == before["notes.txt"]
    assert files["mesh.ply"] not in (before["mesh.ply"], "half of a new mesh")


def test_a_set_up_that_used_the_whole_budget_says_so_as_training_starts(capture_and_gt, tmp_path, capsys):
    cap, _ = capture_and_gt
    assert main(["reconstruct", str(cap), "--out", str(tmp_path / "o"), "--budget-s", "0.001", "--no-gt",
                 "--no-progress"]) == 0
    lines = capsys.readouterr().err.splitlines()
    said = [i for i, line in enumerate(lines) if "warning: the set-up took" in line]
    assert len(said) == 1, lines
    assert "s of the 0.001 s time budget: training makes one step (the fast preset's may take minutes on the cpu)" \
        in lines[said[0]]
    meshing = next(i for i, line in enumerate(lines) if "extracting the mesh" in line)
    assert said[0] < meshing, "said as training starts, not only at the end"
