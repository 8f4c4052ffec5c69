"""The results folder: the fingerprint that keeps incompatible points apart, the lock, results.csv, and a point that
is already done never running twice."""

from __future__ import annotations

import csv
import json

import pytest

from spadscan.protocol.errors import ConfigError
from spadscan.sweep.plan import make_plan
from spadscan.sweep.point import run_point
from spadscan.sweep.spec import load_spec
from spadscan.sweep.store import SweepDir

from sweep_helpers import FAILING_POWER, write_tiny


def fake_result(task, failed_methods=()):
    """A finished point as a worker writes it, with made-up metrics."""
    methods = {}
    for i, m in enumerate(("fast", "reprojection", "space-carving")):
        if m in failed_methods:
            methods[m] = {"status": "failed", "reason": f"{m} found no surface"}
        else:
            methods[m] = {"status": "done", "chamfer_mm": 2.0 * 10 ** i / task.params["views"] * 8,
                          "threshold": None if m == "fast" else 5.0, "steps": 20 if m == "fast" else None}
    failures = [f"{m}: {methods[m]['reason']}" for m in failed_methods]
    return {"id": task.id, "status": "failed" if failures else "done", "reason": "; ".join(failures) or None,
            "scene": task.scene.label, "params": task.params, "methods": methods}


def test_a_changed_base_condition_is_refused_and_a_grown_grid_is_not(tmp_path):
    tiny = write_tiny(tmp_path).read_text()
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    out.write_point(fake_result(next(iter(plan.points.values()))))
    changed = tmp_path / "changed.toml"
    changed.write_text(tiny.replace("views = 12\n", "views = 16\n").replace("steps = 20", "steps = 30"))
    with pytest.raises(ConfigError) as err:
        SweepDir(tmp_path / "out").open(make_plan(load_spec(changed)))
    message = str(err.value)
    assert "another base condition" in message and "base.views: 12 -> 16" in message
    assert "presets.fast.steps: 20 -> 30" in message and "\n" not in message
    with pytest.raises(ConfigError, match="another base condition"):
        SweepDir(tmp_path / "out").check(make_plan(load_spec(changed)))  # the dry run's check, the same verdict
    SweepDir(tmp_path / "out").check(plan)
    grown = tmp_path / "grown.toml"
    grown.write_text(tiny.replace("views = [8, 12]", "views = [8, 12, 16]"))
    again = SweepDir(tmp_path / "out")
    again.open(make_plan(load_spec(grown)))
    again.close()
    assert len(json.loads((tmp_path / "out" / "sweep.json").read_text())["entries"]) == 5


def test_a_folder_that_holds_no_point_takes_a_changed_base_condition(tmp_path):
    """A run that never reached its cluster left sweep.json and no point: nothing in it to keep apart."""
    tiny = write_tiny(tmp_path).read_text()
    out = SweepDir(tmp_path / "out")
    out.open(make_plan(load_spec(write_tiny(tmp_path))))
    out.close()
    changed = tmp_path / "changed.toml"
    changed.write_text(tiny.replace("views = 12\n", "views = 16\n"))
    plan = make_plan(load_spec(changed))
    SweepDir(tmp_path / "out").check(plan)
    again = SweepDir(tmp_path / "out")
    again.open(plan)
    again.close()
    assert json.loads((tmp_path / "out" / "sweep.json").read_text())["fingerprint"] == plan.fingerprint



def test_the_refusal_names_the_original_sweep_file_which_runs_where_the_copy_would_not(tmp_path):
    """A scene that is a relative mesh path is relative to the sweep file's folder: the copy in DIR cannot be run
    where it is, and the advice leads back to the original file, restored from the copy."""
    import shutil

    import trimesh

    sweeps = tmp_path / "sweeps"
    (sweeps / "meshes").mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=2, radius=0.1).export(sweeps / "meshes" / "ball.obj")
    original = sweeps / "one.toml"
    text = write_tiny(tmp_path).read_text().replace('"builtin:sphere"', '"meshes/ball.obj"')
    original.write_text(text)
    plan = make_plan(load_spec(original))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    out.write_point(fake_result(next(iter(plan.points.values()))))
    original.write_text(text.replace("views = 12\n", "views = 16\n"))  # edited in place since
    with pytest.raises(ConfigError, match="another base condition") as err:
        SweepDir(tmp_path / "out").open(make_plan(load_spec(original)))
    message = str(err.value)
    assert str(original.resolve()) in message and str(tmp_path / "out" / "sweep.toml") in message
    assert "\n" not in message
    with pytest.raises(ConfigError, match="no such mesh file"):
        make_plan(load_spec(tmp_path / "out" / "sweep.toml"))  # why the message does not send one to the copy
    shutil.copyfile(tmp_path / "out" / "sweep.toml", original)  # the advice, followed
    again = SweepDir(tmp_path / "out")
    again.open(make_plan(load_spec(original)))
    again.close()

def test_a_folder_of_other_files_is_not_swept_into(tmp_path):
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "thesis.tex").write_text("...")
    with pytest.raises(ConfigError, match="holds other files and no sweep.json"):
        SweepDir(tmp_path / "out").open(plan)
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["thesis.tex"]  # left as it was found


def test_one_sweep_at_a_time_on_a_folder(tmp_path):
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    first = SweepDir(tmp_path / "out")
    first.open(plan)
    try:
        with pytest.raises(ConfigError, match="another `spadscan sweep` is running on this folder"):
            SweepDir(tmp_path / "out").open(plan)
    finally:
        first.close()
    SweepDir(tmp_path / "out").open(plan)  # free again


def test_results_csv_has_a_row_per_entry_with_a_result(tmp_path):
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    tasks = list(plan.points.values())
    out.write_point(fake_result(tasks[0]))
    out.write_point(fake_result(tasks[2], failed_methods=("fast",)))
    assert out.write_results(plan) == 2  # the point in the middle (two entries) has no result yet
    rows = list(csv.DictReader((tmp_path / "out" / "results.csv").open()))
    assert [r["point"] for r in rows] == [tasks[0].id, tasks[2].id]
    assert rows[1]["status"] == "failed" and rows[1]["fast_status"] == "failed" and rows[1]["fast_chamfer_mm"] == ""
    assert rows[1]["reason"] == "fast: fast found no surface" and float(rows[1]["reprojection_chamfer_mm"]) > 0
    assert float(rows[0]["bin_mm"]) == pytest.approx(5.0065, abs=1e-3)  # 33.4 ps of light, one way
    assert not list((tmp_path / "out" / "points").glob(".*"))  # no temporary file left behind


def test_a_point_already_done_is_not_run_again(tmp_path):
    """Dask runs a task again when the worker holding its result dies before the client has it; the point's file
    says it is done, so the second run only reads it."""
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    task = next(t for t in plan.points.values() if t.params["power"] != FAILING_POWER)
    out.write_point(fake_result(task))
    events = []
    result = run_point(task, str(tmp_path / "out"), emit=lambda event, **fields: events.append(event))
    assert events == ["skip"] and result["methods"]["fast"]["steps"] == 20
    assert not list((tmp_path / "out" / "work").iterdir())


def test_a_failing_method_is_recorded_and_the_others_still_run(tmp_path):
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("needs a machine without CUDA: the fast preset is made to fail by asking for it")
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    task = next(t for t in plan.points.values() if t.params["views"] == 8)
    events = []
    result = run_point(task, str(tmp_path / "out"), device="cuda", keep=True,
                       emit=lambda event, **fields: events.append((event, fields.get("stage"))))
    assert result["status"] == "failed" and result["reason"].startswith("fast: device 'cuda' asked for")
    assert "\n" not in result["reason"] and "traceback" not in result["methods"]["fast"]
    assert all(result["methods"][m]["status"] == "done" for m in ("reprojection", "space-carving"))
    assert [e for e, _ in events] == ["start", "stage", "stage", "stage", "stage", "failed"]
    assert json.loads((tmp_path / "out" / "points" / f"{task.id}.json").read_text())["status"] == "failed"
    kept = tmp_path / "out" / "work" / task.id  # --keep: the capture and each method's outputs, under the point's id
    assert result["work"] == str(kept) and [p.name for p in (tmp_path / "out" / "work").iterdir()] == [task.id]
    assert (kept / "capture" / "scan.json").is_file() and (kept / "space-carving" / "mesh.ply").is_file()


def test_a_dry_run_refuses_what_the_run_would_refuse_and_writes_nothing(tmp_path, capsys):
    from spadscan.cli import main

    tiny = write_tiny(tmp_path)
    assert main(["sweep", str(tiny), "--out", str(tmp_path / "fresh"), "--dry-run"]) == 0
    assert capsys.readouterr().out.strip().endswith("to run") and not (tmp_path / "fresh").exists()
    plan = make_plan(load_spec(tiny))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    out.write_point(fake_result(next(iter(plan.points.values()))))
    before = sorted(p.name for p in (tmp_path / "out").iterdir())
    changed = tmp_path / "changed.toml"
    changed.write_text(tiny.read_text().replace("views = 12\n", "views = 16\n"))
    assert main(["sweep", str(changed), "--out", str(tmp_path / "out"), "--dry-run"]) == 1
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("spadscan: error: ")]
    assert len(errors) == 1 and "another base condition" in errors[0]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == before


def test_a_done_result_is_never_replaced_by_a_failed_one(tmp_path):
    """An older attempt that ends last (cut short, its worker dying) must not undo one that finished."""
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    task = next(iter(plan.points.values()))
    out.write_point(fake_result(task))
    stored = out.write_point(fake_result(task, failed_methods=("fast",)))
    assert out.read_point(task.id)["status"] == "done"
    assert stored["status"] == "done"  # what the attempt reports is what is stored


def test_a_rerun_leaves_a_running_attempt_alone_and_waits_for_its_result(tmp_path, monkeypatch):
    """After an interrupt, a scheduler's worker goes on running the point: reopening the folder keeps that attempt's
    work folder, and the re-run's attempt waits for it and takes its result instead of running the point again."""
    import threading

    from spadscan.sweep import point

    plan = make_plan(load_spec(write_tiny(tmp_path)))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    task = next(t for t in plan.points.values() if t.params["power"] != FAILING_POWER)
    in_simulation, release = threading.Event(), threading.Event()
    simulated = []

    def simulate(task, work):  # the first attempt stays in its simulation until released
        simulated.append(work)
        in_simulation.set()
        assert release.wait(60)
        return {"views": task.params["views"]}

    monkeypatch.setattr(point, "_simulate", simulate)
    monkeypatch.setattr(point, "_reconstruct", lambda *args: {"chamfer_mm": 1.0})
    monkeypatch.setattr(point, "_baseline", lambda *args: {"chamfer_mm": 2.0})
    results, second_events, second_acted = {}, [], threading.Event()

    def second_emit(event, **fields):
        second_events.append(event)
        second_acted.set()

    first = threading.Thread(target=lambda: results.setdefault("first", point.run_point(task, str(out.path))))
    second = threading.Thread(target=lambda: results.setdefault(
        "second", point.run_point(task, str(out.path), emit=second_emit)))
    first.start()
    try:
        assert in_simulation.wait(60)
        dead = out.new_work_dir("0123456789abcdef", "gone")  # an attempt that died: no one holds its point
        again = SweepDir(tmp_path / "out")
        again.open(plan)  # the re-run
        again.close()
        assert simulated[0].is_dir() and not dead.exists()
        second.start()
        assert second_acted.wait(60)
    finally:
        release.set()
        first.join(60)
        second.join(60)
    assert len(simulated) == 1 and second_events == ["wait", "skip"]
    assert results["first"]["status"] == "done" and results["second"] == results["first"]
    assert out.read_point(task.id) == results["first"]


def _finished(tmp_path, sweep_file):
    """A folder where every point of `sweep_file` is done (made-up results); returns (its store, the plan)."""
    plan = make_plan(load_spec(sweep_file))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    for task in plan.points.values():
        out.write_point(fake_result(task))
    out.write_results(plan)
    return out, plan


def test_a_sweep_file_that_drops_entries_with_results_is_refused_and_the_folder_kept(tmp_path, capsys):
    """Another grid with the same base condition (or a smaller one) would have made results.csv, sweep.json and
    sweep.toml its own, the first sweep's rows gone from the table and the figure."""
    from spadscan.cli import main

    tiny = write_tiny(tmp_path)
    out, plan = _finished(tmp_path, tiny)
    before = {name: (tmp_path / "out" / name).read_bytes() for name in ("results.csv", "sweep.json", "sweep.toml")}
    other = tmp_path / "other.toml"
    other.write_text(tiny.read_text().replace("power = [1.0, 1e-7]", "ambient = [0.0, 1e-3]"))
    smaller = tmp_path / "smaller.toml"
    smaller.write_text(tiny.read_text().replace("views = [8, 12]", "views = [12]"))
    for sweep_file, lost in ((other, "builtin:sphere power=1e-07"), (smaller, "builtin:sphere views=8")):
        with pytest.raises(ConfigError) as err:
            SweepDir(tmp_path / "out").open(make_plan(load_spec(sweep_file)))
        message = str(err.value)
        assert message.startswith(f"{tmp_path / 'out'} holds results of") and lost in message, message
        assert "--out" in message and "--overwrite" in message and "\n" not in message
        for extra in (["--dry-run"], ["--no-progress"]):  # the dry run says so too
            assert main(["sweep", str(sweep_file), "--out", str(tmp_path / "out"), *extra]) == 1
            errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("spadscan: error: ")]
            assert len(errors) == 1 and "holds results of" in errors[0], errors
    after = {name: (tmp_path / "out" / name).read_bytes() for name in before}
    assert after == before
    # The same sweep resumes, and a grown grid is welcome.
    SweepDir(tmp_path / "out").check(plan)
    grown = tmp_path / "grown.toml"
    grown.write_text(tiny.read_text().replace("views = [8, 12]", "views = [8, 12, 16]"))
    SweepDir(tmp_path / "out").check(make_plan(load_spec(grown)))


def test_overwrite_runs_a_smaller_grid_and_keeps_the_dropped_points(tmp_path):
    tiny = write_tiny(tmp_path)
    out, plan = _finished(tmp_path, tiny)
    smaller = tmp_path / "smaller.toml"
    smaller.write_text(tiny.read_text().replace("views = [8, 12]", "views = [12]"))
    small = make_plan(load_spec(smaller))
    SweepDir(tmp_path / "out").check(small, overwrite=True)
    again = SweepDir(tmp_path / "out")
    again.open(small, overwrite=True)
    again.close()
    assert again.write_results(small) == len(small.entries)
    assert sorted(p.stem for p in (tmp_path / "out" / "points").glob("*.json")) == sorted(plan.points)
    # Its own file gathers the dropped rows again.
    again.open(plan)
    again.close()
    assert again.write_results(plan) == len(plan.entries)


def test_entries_without_a_result_may_be_dropped(tmp_path):
    """A point that never ran loses nothing when a file leaves it out (a run stopped early, its grid trimmed)."""
    tiny = write_tiny(tmp_path)
    plan = make_plan(load_spec(tiny))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.close()
    kept = next(t for t in plan.points.values() if t.params["views"] == 12 and t.params["power"] == 1.0)
    out.write_point(fake_result(kept))
    smaller = tmp_path / "smaller.toml"
    smaller.write_text(tiny.read_text().replace("views = [8, 12]", "views = [12]").replace("power = [1.0, 1e-7]",
                                                                                           "power = [1.0]"))
    again = SweepDir(tmp_path / "out")
    again.open(make_plan(load_spec(smaller)))
    again.close()


def test_closing_the_folder_clears_the_work_folders_of_attempts_that_died_during_the_run(tmp_path):
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    try:
        dead = out.new_work_dir("0123456789abcdef", "gone")  # made after open: a worker killed during this run
        live = out.new_work_dir("fedcba9876543210", "here")
        with out.hold_point("fedcba9876543210") as held:  # an attempt still running holds its point
            assert held
            out.close()
            assert not dead.exists() and live.is_dir()
    finally:
        out.close()
    assert live.is_dir()  # closing twice does nothing more


def test_a_refused_folder_keeps_its_work_folders_when_closed(tmp_path):
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    out = SweepDir(tmp_path / "out")
    out.open(plan)
    out.write_point(fake_result(next(iter(plan.points.values()))))
    dead = out.new_work_dir("0123456789abcdef", "gone")
    out.close()
    dead.mkdir(exist_ok=True)  # the close above clears it: as if a worker died after it
    other = write_tiny(tmp_path).read_text().replace("views = 12\n", "views = 16\n", 1)
    (tmp_path / "other.toml").write_text(other)
    with pytest.raises(ConfigError, match="another base condition"):
        SweepDir(tmp_path / "out").open(make_plan(load_spec(tmp_path / "other.toml")))
    assert dead.is_dir()
