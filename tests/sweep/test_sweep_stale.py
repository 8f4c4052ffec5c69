"""A stored point is reused only where what decides its result is unchanged (fingerprint.py): the resolved preset
config, the baselines' thresholds, the device, spadscan's version and its source. A stale point runs again, its old file
kept until the new result is stored; a failed point runs again only its methods that are not stored done."""

from __future__ import annotations

import json

import pytest

import spadscan
from spadscan.sweep import fingerprint, point, runner
from spadscan.sweep.fingerprint import Digests, Expected, code_digest, source_digest
from spadscan.sweep.plan import make_plan
from spadscan.sweep.point import run_point
from spadscan.sweep.spec import load_spec
from spadscan.sweep.store import SweepDir

from sweep_helpers import write_tiny


def fingerprints(task, device, version):
    return Expected(task, device, version).fingerprints


class Stages:
    """Stand-ins for the simulator, the reconstruction and the baselines that count their calls and can fail;
    `during(method)` runs inside each method's call (to look at the stored point while it runs)."""

    def __init__(self, monkeypatch, failing=(), during=None):
        self.calls: list[str] = []
        self.failing = set(failing)
        self.during = during or (lambda method: None)

        def simulate(task, work):
            self.calls.append("simulate")
            (work / "capture").mkdir()
            return {"views": task.params["views"]}

        def reconstruct(capture, out, **kwargs):
            return self._method(kwargs["preset"], {"chamfer_mm": 5.0, "steps": 20, "stopped_by": "steps",
                                                   "converged": True, "warnings": []})

        def baseline(capture, out, method, **kwargs):
            return self._method(method, {"chamfer_mm": 9.0, "threshold": 5.0, "floor_z_m": 0.0, "warnings": [],
                                         "calibration": {"table": []}})

        monkeypatch.setattr(point, "_simulate", simulate)
        monkeypatch.setattr(point, "reconstruct_capture", reconstruct)
        monkeypatch.setattr(point, "run_baseline", baseline)

    def _method(self, name, report):
        self.calls.append(name)
        self.during(name)
        if name in self.failing:
            raise RuntimeError(f"{name} broke")
        return report


def folder(tmp_path, text=None):
    path = write_tiny(tmp_path)
    if text is not None:
        path.write_text(text(path.read_text()))
    plan = make_plan(load_spec(path))
    store = SweepDir(tmp_path / "out")
    store.open(plan)
    store.close()
    task = next(t for t in plan.points.values() if t.params["power"] == 1.0)
    return plan, store, task


def test_a_point_stored_by_this_code_is_reused_and_so_is_one_stored_before_fingerprints(tmp_path, monkeypatch):
    plan, store, task = folder(tmp_path)
    first = Stages(monkeypatch)
    run_point(task, str(store.path))
    assert first.calls == ["simulate", "fast", "reprojection", "space-carving"]
    stored = store.read_point(task.id)
    assert set(stored["fingerprints"]) == {"fast", "reprojection", "space-carving"}

    again = Stages(monkeypatch)
    run_point(task, str(store.path))
    assert again.calls == []
    # The current layout's file, as the previous spadscan wrote it (no fingerprints; its version and device): reused.
    legacy = {k: v for k, v in stored.items() if k != "fingerprints"}
    (store.points / f"{task.id}.json").write_text(json.dumps(legacy))
    run_point(task, str(store.path))
    assert again.calls == []
    assert task not in runner._points_to_run(plan, store)[0]
    assert Expected(task, "cpu").state(legacy) == "done"


def test_a_changed_preset_default_makes_the_preset_stale_and_it_alone_runs_again(tmp_path, monkeypatch):
    plan, store, task = folder(tmp_path)
    Stages(monkeypatch)
    run_point(task, str(store.path))
    old = (store.points / f"{task.id}.json").read_text()

    changed = fingerprint.preset_config

    def new_defaults(name):
        config = changed(name)
        config.field.carve_threshold += 1.0  # a default the sweep file does not set
        return config

    monkeypatch.setattr(fingerprint, "preset_config", new_defaults)
    todo, stale = runner._points_to_run(plan, store)
    assert task in todo and stale == 1
    # The old result stays in place while the point runs again.
    seen = []
    rerun = Stages(monkeypatch, during=lambda method: seen.append((store.points / f"{task.id}.json").read_text()))
    result = run_point(task, str(store.path))
    assert rerun.calls == ["simulate", "fast"], rerun.calls  # the baselines' results do not depend on it
    assert seen == [old]
    assert result["status"] == "done" and result["fingerprints"] != json.loads(old)["fingerprints"]
    assert runner._points_to_run(plan, store) == ([t for t in todo if t is not task], 0)


def test_changed_default_thresholds_make_the_baselines_that_use_them_stale(tmp_path, monkeypatch):
    plan, store, task = folder(tmp_path, lambda text: text.replace("thresholds = [5, 20]\n", ""))
    Stages(monkeypatch)
    run_point(task, str(store.path))
    monkeypatch.setattr(fingerprint, "CALIBRATION_THRESHOLDS", (4.0, 8.0))
    rerun = Stages(monkeypatch)
    run_point(task, str(store.path))
    assert rerun.calls == ["simulate", "reprojection", "space-carving"]


def test_another_version_or_device_makes_a_point_stale(tmp_path, monkeypatch):
    plan, store, task = folder(tmp_path)
    Stages(monkeypatch)
    stored = run_point(task, str(store.path))
    # Another device: the preset reconstructs there; the baselines run on the CPU all the same.
    assert Expected(task, "cuda").state(stored) == "stale"
    assert set(Expected(task, "cuda").reusable(stored)) == {"reprojection", "space-carving"}
    legacy = {k: v for k, v in stored.items() if k != "fingerprints"}
    assert Expected(task, "cuda").state(legacy) == "stale"

    monkeypatch.setattr(spadscan, "__version__", spadscan.__version__ + ".post1")
    assert Expected(task, "cpu").state(stored) == "stale" and Expected(task, "cpu").state(legacy) == "stale"
    rerun = Stages(monkeypatch)
    assert run_point(task, str(store.path))["spadscan"] == spadscan.__version__
    assert rerun.calls == ["simulate", "fast", "reprojection", "space-carving"]


def test_a_change_to_the_source_between_versions_makes_a_point_stale(tmp_path, monkeypatch):
    """Developing a method changes its code, not spadscan's version: a point stored by other source runs again."""
    plan, store, task = folder(tmp_path)
    Stages(monkeypatch)
    stored = run_point(task, str(store.path))
    assert Expected(task, "cpu").state(stored) == "done"
    assert stored["code"] == code_digest() == runner.point_summary(stored)["code"]  # what the client is told
    assert {inputs["code"] for inputs in Digests().method_inputs(task, "cpu", "1").values()} == {code_digest()}
    monkeypatch.setattr(fingerprint, "code_digest", lambda: "0123456789abcdef")
    assert Expected(task, "cpu").state(stored) == "stale"
    rerun = Stages(monkeypatch)
    run_point(task, str(store.path))
    assert rerun.calls == ["simulate", "fast", "reprojection", "space-carving"]


def test_the_source_digest_follows_each_file_s_name_and_content(tmp_path):
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("x = 1\n")
    b.write_text("y = 2\n")
    base = source_digest([("pkg/a.py", a), ("pkg/b.py", b)])
    assert source_digest([("pkg/b.py", b), ("pkg/a.py", a)]) == base  # in name order, however found
    assert source_digest([("pkg/a2.py", a), ("pkg/b.py", b)]) != base  # a file renamed
    assert source_digest([("pkg/a.py", a)]) != base  # a file removed
    a.write_text("x = 2\n")
    assert source_digest([("pkg/a.py", a), ("pkg/b.py", b)]) != base
    assert code_digest() == code_digest() and len(code_digest()) == 16  # the installed source, read the same way
    a.write_bytes(b"x = 2\r\ny = 3\r\n")
    b.write_bytes(b"x = 2\ny = 3\n")
    assert source_digest([("pkg/a.py", a)]) == source_digest([("pkg/a.py", b)])  # a Windows checkout's line ends


def test_the_code_digest_reads_the_source_files_alone_and_says_where_there_are_none(tmp_path, monkeypatch):
    """An editor's lock file (`.#model.py`, a link to nowhere) or a cache under a dot-folder is no source (a lock
    file made every sweep fail while a method's file was open); an install without source has a digest too."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "m.py").write_text("x = 1\n")
    monkeypatch.setattr(fingerprint, "RESULT_PACKAGES", ("pkg",))
    monkeypatch.syspath_prepend(str(tmp_path))
    base = code_digest()
    (pkg / ".#m.py").symlink_to(tmp_path / "nowhere")
    (pkg / ".hidden").mkdir()
    (pkg / ".hidden" / "x.py").write_text("y = 2\n")
    assert code_digest() == base
    monkeypatch.setattr(fingerprint, "POINT_MODULES", ("gone.py",))
    for p in ((pkg / "sub" / "m.py"), (pkg / "__init__.py")):
        p.unlink()
    assert code_digest() == fingerprint.NO_SOURCE


def test_a_worker_running_other_source_is_said_once(tmp_path):
    summary = runner.Summary(3, 0, code="aaaa")
    ran = lambda worker, code: {"id": "p", "status": "done", "worker": {"name": worker}, "code": code}  # noqa: E731
    assert runner.other_code_line(ran("w1", "aaaa"), summary) is None
    line = runner.other_code_line(ran("w2", "bbbb"), summary)
    assert line.startswith("spadscan sweep: w2 runs other spadscan source than this client (source hash bbbb, here "
                           "aaaa)") and "install the same spadscan on the workers" in line
    assert runner.other_code_line(ran("w2", "bbbb"), summary) is None and summary.other_code == {"w2": "bbbb"}
    assert runner.other_code_line(ran("w3", None), summary) is None  # an earlier version's worker: nothing to say


def test_fingerprints_cover_the_resolved_config_the_thresholds_the_device_and_the_version(tmp_path):
    plan, store, task = folder(tmp_path)
    digests = Digests()
    inputs = digests.method_inputs(task, "cpu", spadscan.__version__)
    assert inputs["fast"]["config"] == digests.resolved_config(task, task.presets[0])
    assert inputs["fast"]["config"]["field"]["resolution"] == 20  # the file's override, in the resolved config
    assert inputs["fast"]["config"]["field"]["carve_threshold"] is not None  # and a default it leaves alone
    assert inputs["fast"]["config"]["metrics_points"] == 5000  # [metrics] points, as the point runs the preset
    assert inputs["fast"]["device"] == "cpu" and inputs["fast"]["spadscan"] == spadscan.__version__
    assert inputs["reprojection"]["thresholds"] == [5.0, 20.0]
    assert fingerprints(task, "cpu", spadscan.__version__) != fingerprints(task, "cpu", "0.0.0")


def stale_aware_point(task, out, device, keep):
    """A point that stores a made-up result as this run's code would (its fingerprints) and says whether it found
    the old one still there."""
    store = SweepDir(out)
    before = store.read_point(task.id)
    result = {"id": task.id, "status": "done", "reason": None, "scene": task.scene.label, "params": task.params,
              "methods": {m: {"status": "done", "chamfer_mm": 1.0} for m in task.record["baselines"]["methods"]
                          + list(task.record["presets"])},
              "fingerprints": Expected(task, device).fingerprints, "old_kept": before is not None}
    store.write_point(result, Expected(task, device))
    return {"id": task.id, "status": "done", "reason": None, "seconds": 0.0, "worker": None}


def test_a_sweep_says_in_one_line_how_many_stored_points_were_stale_and_runs_them_again(tmp_path):
    from distributed import LocalCluster

    plan, store, _ = folder(tmp_path)
    tasks = list(plan.points.values())
    # Two points stored by another version, one by this one.
    for task in tasks:
        version = spadscan.__version__ if task is tasks[0] else "0.0.1"
        store.write_point({"id": task.id, "status": "done", "reason": None, "params": task.params,
                           "methods": {"fast": {"status": "done"}}, "spadscan": version,
                           "fingerprints": fingerprints(task, "cpu", version)})
    lines = []
    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None)
    try:
        summary = runner.run_sweep(plan, store.path, scheduler=cluster.scheduler_address, progress=False,
                                   point=stale_aware_point, log=lines.append)
    finally:
        cluster.close()
    stale = [line for line in lines if "stale" in line]
    assert stale == ["2 stored points are stale (run by another spadscan version or device, or before a preset's or "
                     "a baseline's defaults changed): they run again; each old result is kept until the new one is "
                     "stored, and left out of results.csv until then"], lines
    assert (summary.earlier, summary.ran, summary.done) == (1, 2, 2)
    for task in tasks[1:]:
        assert store.read_point(task.id)["old_kept"] is True
        assert Expected(task, "cpu").state(store.read_point(task.id)) == "done"


def test_a_failed_point_runs_again_only_its_methods_not_done(tmp_path, monkeypatch):
    plan, store, task = folder(tmp_path)
    Stages(monkeypatch, failing={"reprojection"})
    first = run_point(task, str(store.path))
    assert first["status"] == "failed" and first["methods"]["fast"]["status"] == "done"

    rerun = Stages(monkeypatch)
    result = run_point(task, str(store.path))
    assert rerun.calls == ["simulate", "reprojection"], rerun.calls  # fast (a `paper` would take hours) is kept
    assert result["status"] == "done" and result["reason"] is None
    assert result["methods"]["fast"] == first["methods"]["fast"]
    assert list(result["methods"]) == ["fast", "reprojection", "space-carving"]


def test_a_point_whose_worker_died_keeps_the_methods_stored_done(tmp_path, monkeypatch):
    plan, store, task = folder(tmp_path)
    Stages(monkeypatch, failing={"space-carving"})
    run_point(task, str(store.path))
    # Dask gave up on the point's next attempt (its workers died): the failure keeps what was done.
    runner._outcome(RuntimeError("the worker died"), task, store, "cpu")
    stored = store.read_point(task.id)
    assert stored["status"] == "failed" and stored["reason"] == "RuntimeError: the worker died"
    assert set(stored["methods"]) == {"fast", "reprojection"}
    rerun = Stages(monkeypatch)
    run_point(task, str(store.path))
    assert rerun.calls == ["simulate", "space-carving"]


def test_a_dry_run_lists_stale_points_as_to_run(tmp_path, capsys):
    from spadscan.cli import main

    plan, store, task = folder(tmp_path)
    store.write_point({"id": task.id, "status": "done", "reason": None, "params": task.params,
                       "methods": {"fast": {"status": "done"}}, "fingerprints": fingerprints(task, "cpu", "0.0.1")})
    capsys.readouterr()
    assert main(["sweep", str(tmp_path / "tiny.toml"), "--out", str(store.path), "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert f"{task.id}  stale   {task.describe(plan.spec.base)}" in lines, lines
    assert lines[-1] == "3 points, 0 done, 3 to run (1 stale)"


def test_results_csv_leaves_out_a_stale_point_until_it_has_run_again(tmp_path):
    """A sweep stopped before its stale points ran again: one figure must not mix two versions' results, so
    results.csv holds only the current ones (the stale file stays in points/)."""
    plan, store, _ = folder(tmp_path)
    tasks = list(plan.points.values())
    for task in tasks:
        version = spadscan.__version__ if task is tasks[0] else "0.0.1"
        store.write_point({"id": task.id, "status": "done", "reason": None, "scene": task.scene.label,
                           "params": task.params, "methods": {"fast": {"status": "done", "chamfer_mm": 1.0}},
                           "spadscan": version, "fingerprints": fingerprints(task, "cpu", version)})
    rows = store.write_results(plan, runner.current_on(plan, "cpu"))
    points = [line.split(",")[3] for line in (store.path / "results.csv").read_text().splitlines()[1:]]
    assert set(points) == {tasks[0].id} and rows == len(points) > 0
    assert all(store.read_point(task.id) is not None for task in tasks)
    assert store.write_results(plan) == len(plan.entries)  # without the check, every stored point is a row
