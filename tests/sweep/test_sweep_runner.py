"""The client's side of a sweep on a scheduler that other sweeps share."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
import torch

from spadscan.cli import main
from spadscan.protocol.errors import ConfigError
from spadscan.sweep import runner
from spadscan.sweep.plan import make_plan
from spadscan.sweep.runner import emit_event, run_sweep
from spadscan.sweep.spec import load_spec
from spadscan.sweep.store import SweepDir

from sweep_helpers import write_tiny
from test_sweep_store import fake_result


def point_beside_another_sweep(task, out, device, keep):
    """A point that reports its start while a point of another sweep on the same scheduler reports its own."""
    emit_event(str(out) + "-other", task.id, "start")
    emit_event(out, task.id, "start")
    return {"id": task.id, "status": "done", "reason": None, "seconds": 0.0, "worker": None}


def test_a_sweep_logs_only_its_own_events_on_a_shared_scheduler(tmp_path):
    from distributed import LocalCluster

    plan = make_plan(load_spec(write_tiny(tmp_path)))
    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None)
    try:
        summary = run_sweep(plan, tmp_path / "out", scheduler=cluster.scheduler_address, progress=False,
                            point=point_beside_another_sweep)
    finally:
        cluster.close()
    assert summary.done == len(plan.points)
    events = [json.loads(line) for line in (tmp_path / "out" / "log.jsonl").read_text().splitlines()]
    # The events of a task reach the client before its result (one stream, in order): all of this sweep's are here.
    assert sorted(e["point"] for e in events) == sorted(plan.points) and all(e["event"] == "start" for e in events)



def _has_row(out: Path, point_id: str) -> bool:
    """Whether DIR/results.csv holds a row of the point (an absent file holds none; it is replaced atomically)."""
    try:
        return point_id in (out / "results.csv").read_text()
    except FileNotFoundError:
        return False


def point_in_turn(task, out, device, keep):
    """Each point waits until results.csv shows the point before it (order.json beside DIR: id -> the id before, or
    null), then stores its result; one that waits in vain fails, saying so."""
    out = Path(out)
    before = json.loads((out.parent / "order.json").read_text())[task.id]
    deadline = time.monotonic() + 60  # far beyond RESULTS_EVERY_S, however busy the machine
    while before is not None and not _has_row(out, before):
        if time.monotonic() > deadline:
            return {"id": task.id, "status": "failed", "reason": f"results.csv never showed {before}",
                    "seconds": 0.0, "worker": None}
        time.sleep(0.05)
    SweepDir(out).write_point(fake_result(task))
    return {"id": task.id, "status": "done", "reason": None, "seconds": 0.0, "worker": None}


def test_results_csv_catches_up_with_a_finished_point_while_the_next_one_runs(tmp_path, monkeypatch):
    """A point that finishes soon after results.csv was gathered is in it once the throttle's time is up, not only
    when another point finishes: here each point finishes only after the one before is in results.csv."""
    from distributed import LocalCluster

    monkeypatch.setattr(runner, "RESULTS_EVERY_S", 2.0)
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    ids = sorted(plan.points, key=lambda i: (plan.points[i].params["views"], -plan.points[i].params["power"]))
    (tmp_path / "order.json").write_text(json.dumps(dict(zip(ids, [None, *ids[:-1]]))))
    # Threads: every point runs at once, so that only results.csv decides when each ends.
    cluster = LocalCluster(n_workers=1, threads_per_worker=len(ids), processes=False, dashboard_address=None)
    try:
        summary = run_sweep(plan, tmp_path / "out", scheduler=cluster.scheduler_address, progress=False,
                            point=point_in_turn)
    finally:
        cluster.close()
    assert [reason for _, reason in summary.failed] == [] and summary.done == len(ids)
    assert summary.rows == len(plan.entries)


def test_cuda_without_a_scheduler_is_refused_where_torch_sees_no_cuda(tmp_path, monkeypatch):
    """The embedded cluster's worker is this machine: no point is run (to fail at the end) and nothing is written."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    with pytest.raises(ConfigError, match="torch sees no CUDA device") as err:
        run_sweep(plan, tmp_path / "out", device="cuda", progress=False, point=point_beside_another_sweep)
    assert "\n" not in str(err.value) and "--device cpu" in str(err.value)
    assert not (tmp_path / "out").exists()


def test_the_command_refuses_cuda_without_a_scheduler_in_one_line_dry_run_too(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    tiny = str(write_tiny(tmp_path))
    for extra in (["--dry-run"], ["--no-progress"]):
        assert main(["sweep", tiny, "--out", str(tmp_path / "out"), "--device", "cuda", *extra]) != 0
        err = capsys.readouterr().err
        assert "torch sees no CUDA device" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("extra, expected", [
    (["--workers", "0"], "--workers 0 must be at least 1"),
    (["--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"], "--workers sizes the embedded cluster"),
])
def test_the_dry_run_refuses_the_workers_the_run_refuses(tmp_path, capsys, extra, expected):
    tiny = str(write_tiny(tmp_path))
    for mode in (["--dry-run"], ["--no-progress"]):
        assert main(["sweep", tiny, "--out", str(tmp_path / "out"), *extra, *mode]) == 1
        errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("spadscan: error: ")]
        assert len(errors) == 1 and expected in errors[0], errors
    assert not (tmp_path / "out").exists()


def test_a_point_that_killed_its_only_worker_says_so_in_the_singular(tmp_path):
    from distributed import KilledWorker

    plan = make_plan(load_spec(write_tiny(tmp_path)))
    store = SweepDir(tmp_path / "out")
    store.open(plan)
    store.close()
    task = next(iter(plan.points.values()))
    result = runner._outcome(KilledWorker(task.id, None, 0), task, store, "cpu")
    assert result["reason"] == "the worker running it died; its log says why"
    result = runner._outcome(KilledWorker(task.id, None, 2), task, store, "cpu")
    assert result["reason"] == "the worker running it died each time it was tried (3 workers); their logs say why"


def point_with_results(task, out, device, keep):
    """A point whose fast preset warned twice and whose baselines gave results (none at the lowest power)."""
    if task.params["power"] < 1e-3:
        return {"id": task.id, "status": "failed", "reason": "every method: no return", "seconds": 0.0,
                "worker": None, "methods": {m: {"status": "failed", "chamfer_mm": None, "warnings": 0}
                                            for m in ("fast", "reprojection", "space-carving")}}
    return {"id": task.id, "status": "done", "reason": None, "seconds": 0.0, "worker": None,
            "methods": {"fast": {"status": "done", "chamfer_mm": 5.2194, "warnings": 2},
                        "reprojection": {"status": "done", "chamfer_mm": 22.03, "warnings": 0},
                        "space-carving": {"status": "failed", "chamfer_mm": None, "warnings": 0}}}


def test_without_a_progress_bar_each_finished_point_is_a_line(tmp_path):
    """A sweep left running under nohup shows each point as it ends: its id, status, Chamfer per method, warnings."""
    from distributed import LocalCluster

    plan = make_plan(load_spec(write_tiny(tmp_path)))
    lines: list[str] = []
    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None)
    try:
        run_sweep(plan, tmp_path / "out", scheduler=cluster.scheduler_address, progress=False, log=lines.append,
                  point=point_with_results)
    finally:
        cluster.close()
    finished = [line for line in lines if line.startswith("point ")]
    assert len(finished) == len(plan.points) == 3, lines
    assert {line.split("[")[1].split("]")[0] for line in finished} == set(plan.points)
    assert sorted(line.split()[1] for line in finished) == ["1/3", "2/3", "3/3"]
    done = [line for line in finished if ": done; " in line]
    assert len(done) == 2 and all(line.endswith("fast 5.22 mm, reprojection 22 mm, space-carving failed; "
                                                 "2 warnings (fast)") for line in done), done
    (failed,) = [line for line in finished if ": failed" in line]
    assert failed.endswith("power=1e-07: failed; every method: no return"), failed


def test_a_point_dask_gave_up_on_after_it_was_stored_done_is_reported_done(tmp_path):
    """Dask can give up on a task (its worker died) after the attempt stored the point as done: the client's account
    must follow points/<id>.json, not Dask."""
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    task = next(iter(plan.points.values()))
    store = SweepDir(tmp_path / "out")
    store.open(plan)
    try:
        store.write_point(fake_result(task))
        result = runner._outcome(RuntimeError("worker lost"), task, store, "cpu")
    finally:
        store.close()
    assert result["status"] == "done" and result["reason"] is None, result
    assert result["methods"]["fast"]["status"] == "done"
    assert json.loads((store.points / f"{task.id}.json").read_text())["status"] == "done"
    log = (store.path / "log.jsonl").read_text() if (store.path / "log.jsonl").exists() else ""
    assert '"event": "failed"' not in log


@pytest.mark.parametrize("gpu, expected", [(True, "cuda"), (False, "cpu")])
def test_auto_on_the_local_cluster_is_the_device_its_points_run_on(monkeypatch, gpu, expected):
    """The embedded cluster's machine runs the points: 'auto' is resolved there as the reconstruction resolves it, so
    that a GPU gets one worker (not one per core sharing it) and the points store the device they ran on."""
    from spadscan.sweep.checks import local_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: gpu)
    assert local_device("auto") == expected
    assert local_device("cpu") == "cpu"


def test_points_run_on_the_cpu_are_reused_by_an_auto_run_on_a_machine_without_a_gpu(tmp_path, monkeypatch, capsys):
    """A point stored by a --device cpu run is current for --device auto where torch sees no GPU (the same device):
    the dry run lists it done, not stale."""
    from spadscan.sweep.fingerprint import Expected

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    tiny = write_tiny(tmp_path)
    plan = make_plan(load_spec(tiny))
    store = SweepDir(tmp_path / "out")
    store.open(plan)
    task = next(iter(plan.points.values()))
    store.write_point({**fake_result(task), "device": "cpu", "fingerprints": Expected(task, "cpu").fingerprints})
    store.close()
    capsys.readouterr()
    assert main(["sweep", str(tiny), "--out", str(tmp_path / "out"), "--device", "auto", "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any(line.startswith(f"{task.id}  done") for line in lines), lines
