"""Worker processes on one captures root: exactly once, kill -9 and retry, corrupt captures, clean stops.

The jobs here run `marker_recon` (below) instead of the torch reconstruction: it leaves a marker file when it starts
and when it ends, and sleeps in between, which is what the queue's guarantees are about.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from spadscan.cli import main as cli_main
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.watcher import SETTLE_S
from spadscan.worker.worker_config import WorkerConfig

from process_helpers import reaped
from test_watcher import make_scan

HERE = Path(__file__).resolve().parent
RECON = "test_worker_process:marker_recon"


def marker_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                started=None):
    """A stand-in reconstruction: markers `<scan>.<pid>.start/.end` in $MARKERS, a report in `out`."""
    markers = Path(os.environ["MARKERS"])
    name = f"{Path(capture).name}.{os.getpid()}"
    (markers / f"{name}.start").write_text("")
    if os.environ.get("RECON_FAIL") == Path(capture).name:
        raise RuntimeError("simulated crash")
    if os.environ.get("PROGRESS_BAR"):  # what the reconstruction's progress bar writes to the job's log
        print(os.environ["PROGRESS_BAR"], end="\r", file=sys.stderr, flush=True)
    if os.environ.get("RELEASE"):  # hold the job until the test lets it end
        while not Path(os.environ["RELEASE"]).exists():
            time.sleep(0.02)
    time.sleep(float(os.environ.get("SLEEP_S", "0")))
    report = {"preset": preset, "chamfer_mm": 1.5, "capture": str(capture)}
    (Path(out) / "report.json").write_text(json.dumps(report))
    (markers / f"{name}.end").write_text("")
    return report


LAUNCH = """
import asyncio, sys
from spadscan.worker.pool import run_worker
from spadscan.worker.worker_config import WorkerConfig
root, once, lease = sys.argv[1], sys.argv[2] == "once", float(sys.argv[3])
if len(sys.argv) > 4:  # pretend to be another machine sharing the filesystem
    import spadscan.worker.holder as holder
    holder.socket.gethostname = lambda: sys.argv[4]
config = WorkerConfig(root=root, processes=2, once=once, poll_s=0.1, lease_s=lease, max_attempts=3,
                      recon=%r, stop_grace_s=5)
asyncio.run(run_worker(config))
""" % RECON


def start_worker(root: Path, markers: Path, *, once: bool, sleep_s: float, lease_s: float = 30.0,
                 host: str | None = None, env: dict[str, str] | None = None):
    """A worker process (2 job processes at once, stand-in reconstruction `marker_recon`); `env`: variables added
    to its environment."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")]),
           "MARKERS": str(markers), "SLEEP_S": str(sleep_s), **(env or {})}
    args = [str(root), "once" if once else "serve", str(lease_s)] + ([host] if host else [])
    return subprocess.Popen([sys.executable, "-c", LAUNCH, *args], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def markers_of(markers: Path, scan: str, kind: str) -> list[int]:
    """Pids of the job processes that left a `kind` marker for `scan`."""
    return [int(p.name.split(".")[1]) for p in markers.glob(f"{scan}.*.{kind}")]


def wait_for(predicate, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("timed out waiting")
        time.sleep(0.05)


def pid_alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.fixture
def markers(tmp_path):
    d = tmp_path / "markers"
    d.mkdir()
    return d


def test_two_workers_run_each_job_exactly_once(tmp_path, markers):
    root = tmp_path / "captures"
    root.mkdir()
    scans = [f"scan{i}" for i in range(6)]
    for s in scans:
        make_scan(root, s)
    with reaped(*(start_worker(root, markers, once=True, sleep_s=0.3) for _ in range(2))) as workers:
        logs = [w.communicate(timeout=120)[0] for w in workers]
    assert [w.returncode for w in workers] == [0, 0], logs
    for s in scans:
        assert len(markers_of(markers, s, "start")) == 1, f"{s} started more than once"
        assert len(markers_of(markers, s, "end")) == 1
        result = root / s / "recon" / f"{s}-fast"
        assert json.loads((result / "report.json").read_text())["capture"].endswith(s)
        assert (result / "job.log").exists() and (result / "job.json").exists()
        assert not [p for p in (root / s / "recon").iterdir() if p.name.startswith(".")], "no scratch left"
    assert Queue.for_root(root).counts() == {"queued": 0, "running": 0, "done": 6, "failed": 0}


@pytest.mark.parametrize("where", ["same machine", "another machine"])
def test_a_killed_workers_job_is_retried_by_another(tmp_path, markers, where):
    """On one machine the dead holder is seen at once; from another machine, once its lease expires."""
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    first = start_worker(root, markers, once=False, sleep_s=60, lease_s=2.0)
    try:
        wait_for(lambda: markers_of(markers, "s", "start"))
        (orphan,) = markers_of(markers, "s", "start")
        first.kill()  # kill -9: no chance to release the lease
        first.communicate(timeout=30)
        wait_for(lambda: not pid_alive(orphan), 30)  # its job process notices and exits
        killed = time.monotonic()
        host = "elsewhere" if where == "another machine" else None
        with reaped(start_worker(root, markers, once=True, sleep_s=0.1, lease_s=2.0, host=host)) as (second,):
            log = second.communicate(timeout=120)[0]
        waited = time.monotonic() - killed
        assert second.returncode == 0, log
    finally:
        if first.poll() is None:
            first.kill()
            first.communicate()
    assert len(markers_of(markers, "s", "start")) == 2
    assert len(markers_of(markers, "s", "end")) == 1, "the job ran to its end exactly once"
    (row,) = Queue.for_root(root).statuses()
    assert (row.state, row.attempts) == ("done", 2)
    recs = Queue.for_root(root).records("s-fast")
    assert [r["outcome"] for r in recs] == ["lost", "done"]
    assert (recs[0]["host"], recs[0]["pid"]) == (socket.gethostname(), first.pid), "the killed worker held it"
    said = f"s-fast: worker {recs[0]['host']} pid {first.pid} "
    if where == "same machine":
        assert "died mid-job" in recs[0]["error"]
        assert f"{said}died mid-job; queued again" in log, log
    else:
        assert "stopped renewing its lease" in recs[0]["error"] and recs[1]["host"] == "elsewhere"
        assert re.search(rf"{re.escape(said)}stopped renewing its lease \(\d+ s > 2 s\); queued again", log), log
        assert "died mid-job" not in log, "from another machine, a silent holder is not known to have died"
        assert waited > 1.0, "the job is taken over only after the lease has expired"


def test_sigterm_stops_the_job_and_gives_it_back(tmp_path, markers):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    worker = start_worker(root, markers, once=False, sleep_s=60)
    try:
        wait_for(lambda: markers_of(markers, "s", "start"))
        (child,) = markers_of(markers, "s", "start")
        worker.send_signal(signal.SIGTERM)
        log = worker.communicate(timeout=60)[0]
    finally:
        if worker.poll() is None:
            worker.kill()
            worker.communicate()
    assert worker.returncode == 0, log
    assert not pid_alive(child)
    assert "back in the queue" in log
    q = Queue.for_root(root)
    assert q.counts()["queued"] == 1 and q.attempts("s-fast") == 0, "a stop does not use up an attempt"
    assert not (root / "s" / "recon" / "s-fast").exists()


def _corrupt_chunk(scan: Path) -> None:
    (scan / "chunk-000000" / "hists.npy").write_bytes(b"\x93NUMPY garbage")


@pytest.mark.usefixtures("recon_stand_ins")
def test_bad_captures_fail_their_jobs_and_the_worker_goes_on(tmp_path, markers, arun, monkeypatch):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "good")
    make_scan(root, "corrupt")
    _corrupt_chunk(root / "corrupt")
    make_scan(root, "crashes")
    (root / "broken").mkdir()
    (root / "broken" / "scan.json").write_text("[]")
    long_ago = time.time() - SETTLE_S - 1  # not a copy still under way: it has stood unchanged
    for path in (root / "broken" / "scan.json", root / "broken"):
        os.utime(path, (long_ago, long_ago))
    monkeypatch.setenv("MARKERS", str(markers))
    monkeypatch.setenv("RECON_FAIL", "crashes")
    lines = []
    config = WorkerConfig(root=root, processes=2, once=True, poll_s=0.1, max_attempts=2, recon=RECON)
    settled = arun(Worker(config, log=lines.append).run(), timeout_s=120)
    assert settled == {"good-fast": "done", "corrupt-fast": "failed", "crashes-fast": "failed",
                       "broken-fast": "failed"}
    rows = {r.id: r for r in Queue.for_root(root).statuses()}
    assert "hists.npy" in rows["corrupt-fast"].error and rows["corrupt-fast"].attempts == 1
    assert "expected a JSON object" in rows["broken-fast"].error
    assert rows["crashes-fast"].attempts == 2 and "RuntimeError: simulated crash" in rows["crashes-fast"].error
    assert rows["good-fast"].result == str(root / "good" / "recon" / "good-fast")
    assert not markers_of(markers, "corrupt", "start"), "a corrupt capture never reaches the reconstruction"
    assert any("corrupt-fast failed" in line for line in lines)


def test_status_lists_jobs_as_a_table_and_as_json(tmp_path, capsys):
    root = tmp_path / "captures"
    root.mkdir()
    q = Queue.for_root(root)
    from spadscan.worker.watcher import JobOptions, scan_once

    make_scan(root, "a")
    make_scan(root, "b")
    scan_once(root, q, JobOptions())
    c = q.claim()
    q.fail(c, "a.npy: corrupt", retry=False)
    assert cli_main(["worker", "--root", str(root), "--status"]) == 0
    out = capsys.readouterr().out
    assert "a-fast" in out and "failed" in out and "a.npy: corrupt" in out and "b-fast" in out
    assert cli_main(["worker", "--root", str(root), "--status", "--json"]) == 0
    rows = {r["id"]: r for r in json.loads(capsys.readouterr().out)}
    assert rows["a-fast"]["state"] == "failed" and rows["b-fast"]["state"] == "queued"


def test_status_shows_how_far_a_running_job_has_got(tmp_path, markers, capsys):
    """A worker runs a job whose reconstruction has drawn its progress bar: --status shows the bar's reading on the
    job's row (and --json as `progress`); once the job is done, its result."""
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "a")
    bar = ("reconstruct (fast):  58%|#####     | 70/120 s [01:10<00:50, step=340, loss=0.912, chamfer=2.10mm, "
           "scored=checkpoint 128-cell mesh; 30k points]")
    release = tmp_path / "release"
    worker = start_worker(root, markers, once=True, sleep_s=0, env={"PROGRESS_BAR": bar, "RELEASE": str(release)})
    try:
        wait_for(lambda: markers_of(markers, "a", "start"))

        def row_of_a() -> str:
            assert cli_main(["worker", "--root", str(root), "--status"]) == 0
            return next(line for line in capsys.readouterr().out.splitlines() if line.startswith("a-fast"))

        wait_for(lambda: "step 340" in row_of_a())  # the bar reaches the log once the job's process has flushed it
        row = row_of_a()
        assert row.split()[1] == "running"
        assert "reconstruct (fast): 70/120 s, step 340, loss 0.912, Chamfer 2.10 mm" in row and "[01:10 elapsed" in row
        assert cli_main(["worker", "--root", str(root), "--status", "--json"]) == 0
        (row,) = json.loads(capsys.readouterr().out)
        assert row["progress"]["done"] == 70 and row["progress"]["chamfer_mm"] == 2.10
    finally:
        release.write_text("")
        worker.communicate(timeout=120)
    assert cli_main(["worker", "--root", str(root), "--status", "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["state"] == "done" and "progress" not in row, "a finished job shows its result, not its progress"


def test_status_lists_jobs_whose_queue_files_are_damaged(tmp_path, capsys):
    """Empty or foreign attempt records and empty job files: every row is printed, the damage named, no traceback."""
    from spadscan.worker.watcher import JobOptions, scan_once

    root = tmp_path / "captures"
    root.mkdir()
    for name in ("empty", "list", "odd", "nojob", "ok"):
        make_scan(root, name)
    q = Queue.for_root(root)
    scan_once(root, q, JobOptions())
    while (c := q.claim()) is not None:
        if c.job.scan == "odd":
            q.fail(c, "boom", retry=False)
        else:
            q.finish(c, f"/results/{c.job.scan}")
    (record,) = (q.path / "attempts" / "empty-fast").glob("*.json")
    record.write_text("")
    (record,) = (q.path / "attempts" / "list-fast").glob("*.json")
    record.write_text("[1, 2]")
    (record,) = (q.path / "attempts" / "odd-fast").glob("*.json")
    record.write_text('{"outcome": "failed", "error": 5, "started_unix": null}')
    (q.path / "done" / "nojob-fast.json").write_text("")
    (q.path / "ids" / "ok-fast.json").unlink()  # a hard link of the job file: emptying it would empty both
    (q.path / "ids" / "ok-fast.json").write_text("")
    assert cli_main(["worker", "--root", str(root), "--status"]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    lines = {line.split()[0]: line for line in captured.out.splitlines()}
    assert "result: unknown (unreadable attempt record" in lines["empty-fast"]
    assert "result: unknown (unreadable attempt record" in lines["list-fast"]
    assert lines["odd-fast"].split()[1:4] == ["failed", "1", "-"] and lines["odd-fast"].endswith("  5")
    assert "/results/nojob" in lines["nojob-fast"] and "unreadable job file" in lines["nojob-fast"]
    assert lines["ok-fast"].endswith("/results/ok (no longer there)")  # a made-up folder
    assert cli_main(["worker", "--root", str(root), "--status", "--json"]) == 0
    rows = {r["id"]: r for r in json.loads(capsys.readouterr().out)}
    assert rows["empty-fast"]["result"] is None and "unreadable attempt record" in rows["empty-fast"]["notes"][0]
    assert rows["ok-fast"]["notes"] == []


def test_status_marks_running_jobs_whose_worker_seems_gone(tmp_path, capsys):
    """A dead holder on this machine or an expired lease: 'stale'; missed heartbeats within the lease: 'running?'."""
    from spadscan.worker.holder import Holder
    from spadscan.worker.jobs import Job

    root = tmp_path / "captures"
    root.mkdir()
    queue = Queue.for_root(root, lease_s=60)
    names = ("dead", "expired", "silent", "live")
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    elsewhere = Holder("another-host", 4242, "other-boot", "pid:[1]", "1")  # never judged alive or dead from here
    holders = {"dead": Holder(**{**Holder.current().to_dict(), "pid": gone.pid, "pid_start": ""}),
               "expired": elsewhere, "silent": elsewhere, "live": Holder.current()}
    claims = {}
    for name in names:  # one at a time: a claim takes the first queued job by name
        make_scan(root, name)
        queue.enqueue(Job(id=f"{name}-fast", scan=name))
        claims[name] = queue.claim(holders[name])
    now = time.time()
    os.utime(claims["expired"].path, (now - 90, now - 90))
    os.utime(claims["silent"].path, (now - 40, now - 40))
    assert cli_main(["worker", "--root", str(root), "--status"]) == 0
    out = capsys.readouterr().out
    assert "4 running (2 stale: their worker is gone)" in out.splitlines()[-2]  # not all four at work
    rows = {line.split()[0]: line for line in out.splitlines()}
    assert rows["dead-fast"].split()[1] == "stale" and f"pid {gone.pid} died mid-job" in rows["dead-fast"]
    assert rows["expired-fast"].split()[1] == "stale" and "stopped renewing its lease (90 s > 60 s)" in rows[
        "expired-fast"] and "the next worker to look at the queue takes it over" in rows["expired-fast"]
    assert rows["silent-fast"].split()[1] == "running?"
    assert "worker silent for 40 s (its lease of 60 s has not expired yet)" in rows["silent-fast"]
    assert rows["live-fast"].split()[1] == "running" and rows["live-fast"].rstrip().endswith("-")
    assert cli_main(["worker", "--root", str(root), "--status", "--json"]) == 0
    by_id = {r["id"]: r for r in json.loads(capsys.readouterr().out)}
    assert {k: (r["state"], r["shown_state"]) for k, r in by_id.items()} == {
        "dead-fast": ("running", "stale"), "expired-fast": ("running", "stale"),
        "silent-fast": ("running", "running?"), "live-fast": ("running", "running")}
    assert by_id["live-fast"]["stale"] is None and "died mid-job" in by_id["dead-fast"]["stale"]
    assert queue.counts()["running"] == 4, "a status query takes nothing over"


def test_the_command_refuses_a_missing_root_and_an_unknown_preset(tmp_path, capsys):
    assert cli_main(["worker", "--root", str(tmp_path / "nope"), "--once"]) == 1
    assert "captures root does not exist" in capsys.readouterr().err
    assert cli_main(["worker", "--root", str(tmp_path), "--once", "--preset", "slow"]) == 1
    assert "unknown preset 'slow'" in capsys.readouterr().err
    assert not (tmp_path / ".queue").exists(), "nothing queued with a bad preset"


def options_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                started=None):
    """A stand-in reconstruction that fails on 'cuda' as the real one does without a GPU, and reports its options."""
    from spadscan.protocol.errors import SpadscanError

    if device == "cuda":
        raise SpadscanError("device 'cuda' asked for, but torch sees no CUDA device (use --device cpu or auto)")
    report = {"device": device, "seed": seed, "steps": steps}
    (Path(out) / "report.json").write_text(json.dumps(report))
    return report


def test_bad_seed_and_device_are_refused_before_anything_is_queued(tmp_path, capsys, monkeypatch):
    import torch

    make_scan(tmp_path, "s")
    assert cli_main(["worker", "--root", str(tmp_path), "--once", "--seed", "-1"]) == 1
    err = capsys.readouterr().err
    assert "seed -1 must be an integer in [0, 9223372036854775807]" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / ".queue").exists()
    assert cli_main(["worker", "--root", str(tmp_path), "--once", "--seed", str(2**64)]) == 1  # torch's limit
    err = capsys.readouterr().err
    assert f"seed {2**64} must be an integer in [0, {2**63 - 1}]" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / ".queue").exists()
    assert cli_main(["worker", "--root", str(tmp_path), "--once", "--budget-s", "1e9"]) == 1  # over a week
    err = capsys.readouterr().err
    assert "time budget 1000000000.0 s must be" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / ".queue").exists()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert cli_main(["worker", "--root", str(tmp_path), "--once", "--device", "cuda"]) == 1
    err = capsys.readouterr().err
    assert "torch sees no CUDA device (use --device cpu or auto)" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / ".queue").exists()
    assert cli_main(["worker", "--root", str(tmp_path), "--retry-failed", "--device", "cuda"]) == 1
    assert "no CUDA device" in capsys.readouterr().err, "an option given with --retry-failed is checked too"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # a GPU machine
    assert cli_main(["worker", "--root", str(tmp_path), "--retry-failed", "--device", "cuda"]) == 0
    assert capsys.readouterr().out.strip() == "no failed jobs"


def test_checking_the_options_loads_torch_only_for_cuda(tmp_path):
    """The worker process stays light: torch is loaded in the job processes, and in the worker only to see whether
    a GPU asked for is there."""
    code = ("import sys; from spadscan.worker.worker_config import WorkerConfig; "
            "from spadscan.worker.watcher import JobOptions; "
            "WorkerConfig(root=sys.argv[1], options=JobOptions(device='cpu', seed=3)).check(); "
            "WorkerConfig(root=sys.argv[1]).check(); print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "False", out.stderr


@pytest.mark.usefixtures("recon_stand_ins")
def test_retry_failed_queues_failed_jobs_with_the_options_given(tmp_path, arun, capsys):
    from spadscan.worker.watcher import JobOptions, scan_once

    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    scan_once(root, Queue.for_root(root), JobOptions(device="cuda", seed=7, steps=5))  # queued by an earlier worker

    def run_once() -> dict:
        # This worker's own options (device auto) apply to scans it queues, not to the job already queued.
        config = WorkerConfig(root=root, once=True, poll_s=0.1, recon="test_worker_process:options_recon")
        return arun(Worker(config, log=lambda line: None).run(), timeout_s=120)

    assert run_once() == {"s-fast": "failed"}
    assert cli_main(["worker", "--root", str(root), "--retry-failed"]) == 0
    assert capsys.readouterr().out.strip() == "queued again: s-fast (with their own options)"
    assert run_once() == {"s-fast": "failed"}, "retried as it was queued: device cuda again"
    assert cli_main(["worker", "--root", str(root), "--retry-failed", "--device", "cpu"]) == 0
    assert capsys.readouterr().out.strip() == "queued again: s-fast (with --device cpu)"
    assert run_once() == {"s-fast": "done"}
    report = json.loads((root / "s" / "recon" / "s-fast" / "report.json").read_text())
    assert report == {"device": "cpu", "seed": 7, "steps": 5}, "the options not given keep the job's own values"


def test_help_says_what_happens_to_options(capsys):
    with pytest.raises(SystemExit):
        cli_main(["worker", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "Options are frozen into each job when it is queued" in text
    assert "--retry-failed --device cpu" in text and "replace the jobs' own values" in text


def test_jobs_find_the_ground_truth_a_capture_names(tmp_path):
    from spadscan.worker.jobs import ground_truth

    mesh = tmp_path / "gt.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert ground_truth({"scene": {"ground_truth": str(mesh)}}, tmp_path) == (mesh, None)  # import-lcspc
    assert ground_truth({"scene": {"mesh": str(mesh)}}, tmp_path) == (mesh, None)  # simulate MESH
    exported, note = ground_truth({"scene": {"builtin": "sphere"}}, tmp_path)  # simulate builtin:NAME
    assert exported == tmp_path / "ground_truth.ply" and exported.stat().st_size > 0 and note is None
    assert ground_truth({}, tmp_path) == (None, None), "no ground truth named: nothing to say"


def test_a_ground_truth_that_cannot_be_used_is_a_note_not_a_failure(tmp_path):
    from spadscan.worker.jobs import ground_truth

    flat = tmp_path / "flat.obj"
    flat.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")  # vertices, no faces
    assert ground_truth({"scene": {"ground_truth": str(flat)}}, tmp_path) == (
        None, f"{flat}: holds no triangles; no metrics")
    gone = tmp_path / "gone.obj"
    assert ground_truth({"scene": {"mesh": str(gone)}}, tmp_path) == (
        None, f"{gone}: no such ground-truth mesh; no metrics")
    gt, note = ground_truth({"scene": {"builtin": "no-such-scene"}}, tmp_path)
    assert gt is None and note.startswith("built-in scene 'no-such-scene': ") and note.endswith("; no metrics")


def gt_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                started=None):
    """A stand-in reconstruction that writes its report as the real one does (report.json, report.html)."""
    from spadscan.worker.report.report_html import write_report_html
    from spadscan.worker.report.report_json import write_report

    report = {"preset": preset, "capture": str(capture), "gt_given": None if gt is None else str(gt)}
    write_report(out, report)
    write_report_html(report, out)
    return report


@pytest.mark.usefixtures("recon_stand_ins")
def test_jobs_whose_ground_truth_cannot_be_used_still_reconstruct(tmp_path, arun):
    root = tmp_path / "captures"
    root.mkdir()
    flat = tmp_path / "flat.obj"
    flat.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    named = {"flat": str(flat), "gone": str(tmp_path / "gone.obj")}
    for name, mesh in named.items():
        make_scan(root, name)
        manifest = root / name / "scan.json"
        manifest.write_text(json.dumps({**json.loads(manifest.read_text()), "scene": {"ground_truth": mesh}}))
    lines = []
    config = WorkerConfig(root=root, once=True, poll_s=0.1, recon="test_worker_process:gt_recon")
    assert arun(Worker(config, log=lines.append).run(), timeout_s=120) == {"flat-fast": "done", "gone-fast": "done"}
    notes = {"flat": f"{flat}: holds no triangles; no metrics",
             "gone": f"{tmp_path / 'gone.obj'}: no such ground-truth mesh; no metrics"}
    for name, note in notes.items():
        result = root / name / "recon" / f"{name}-fast"
        report = json.loads((result / "report.json").read_text())
        assert report["ground_truth_note"] == note and report["gt_given"] is None
        assert note in (result / "report.html").read_text()
        assert json.loads((result / "job.json").read_text())["gt_note"] == note
        assert any(f"{name}-fast done" in line and f"(ground truth: {note})" in line for line in lines), lines


def test_a_job_whose_worker_is_already_gone_exits_at_once(tmp_path, markers):
    """The job is told its worker's pid: when that is not its parent (the worker died before the job got under way,
    so the job was reparented), it exits before reconstructing anything."""
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")]),
           "MARKERS": str(markers)}
    outcome = tmp_path / "outcome.json"

    def job(parent_pid: int) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "spadscan.worker.jobs", "--job", json.dumps({"id": "s-fast", "scan": "s"}),
             "--root", str(root), "--out", str(tmp_path / "out"), "--outcome", str(outcome),
             "--parent-pid", str(parent_pid), "--recon", RECON], env=env, capture_output=True, text=True, timeout=60)

    gone = job(os.getppid())  # a live process, but not the job's parent
    assert gone.returncode == 4, gone.stderr
    assert not outcome.exists() and not markers_of(markers, "s", "start"), "nothing ran"
    ran = job(os.getpid())  # its real parent
    assert ran.returncode == 0, ran.stderr
    assert json.loads(outcome.read_text())["ok"] and markers_of(markers, "s", "start")


@pytest.mark.usefixtures("recon_stand_ins")
def test_partial_results_of_dead_claims_are_removed_and_live_ones_kept(tmp_path, markers, arun, monkeypatch):
    """A worker removes the scratch folder a dead worker left, never one of a job another worker is running."""
    from spadscan.worker.jobs import Job, scratch_path
    from spadscan.worker.holder import Holder

    root = tmp_path / "captures"
    root.mkdir()
    for name in ("dead", "live"):
        make_scan(root, name)
    queue = Queue.for_root(root, lease_s=3600)
    for name in ("dead", "live"):
        queue.enqueue(Job(id=f"{name}-fast", scan=name))
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead_claim = queue.claim(Holder(**{**Holder.current().to_dict(), "pid": gone.pid, "pid_start": ""}))
    live_claim = queue.claim(Holder("another-host", 4242, "other-boot", "pid:[1]", "1"))  # lease held for an hour
    folders = {"dead": scratch_path(dead_claim.job, root, dead_claim.token),
               "live": scratch_path(live_claim.job, root, live_claim.token),
               "outside the queue": scratch_path(dead_claim.job, root)}
    for folder in folders.values():
        folder.mkdir(parents=True)
        (folder / "mesh.ply").write_text("partial")
    monkeypatch.setenv("MARKERS", str(markers))
    lines = []
    worker = Worker(WorkerConfig(root=root, poll_s=0.1, lease_s=3600, recon=RECON), log=lines.append)

    async def until_dead_job_is_redone():
        stop = asyncio.Event()
        task = asyncio.create_task(worker.run(stop))
        while "dead-fast" not in worker.settled and not task.done():
            await asyncio.sleep(0.05)
        stop.set()
        return await task

    assert arun(until_dead_job_is_redone(), timeout_s=120) == {"dead-fast": "done"}
    assert not folders["dead"].exists(), "the dead worker's partial result is gone"
    assert (folders["live"] / "mesh.ply").read_text() == "partial", "a running job's scratch folder is kept"
    assert folders["outside the queue"].exists(), "a folder no claim names is not the queue's to remove"
    assert (root / "dead" / "recon" / "dead-fast" / "report.json").is_file()
    assert any("removed the partial result" in line for line in lines)


def scored_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                started=None):
    """A stand-in reconstruction that reads the ground truth it is given and records its path, as the real one does
    (report.json and report.html)."""
    from spadscan.worker.report.report_html import write_report_html
    from spadscan.worker.report.report_json import write_report

    assert Path(gt).stat().st_size > 0
    report = {"preset": preset, "capture": str(capture), "ground_truth": str(gt)}
    write_report(out, report)
    write_report_html(report, out)
    return report


@pytest.mark.usefixtures("recon_stand_ins")
def test_every_path_a_published_result_records_is_valid_after_publishing(tmp_path, arun):
    """A built-in scene's ground truth is exported into the job's folder: the results name it where it is once
    published, not in the scratch folder the job was written into."""
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    manifest = root / "s" / "scan.json"
    manifest.write_text(json.dumps({**json.loads(manifest.read_text()), "scene": {"builtin": "sphere"}}))
    config = WorkerConfig(root=root, once=True, poll_s=0.1, recon="test_worker_process:scored_recon")
    assert arun(Worker(config, log=lambda line: None).run(), timeout_s=120) == {"s-fast": "done"}
    result = root / "s" / "recon" / "s-fast"
    report = json.loads((result / "report.json").read_text())
    job = json.loads((result / "job.json").read_text())
    assert report["ground_truth"] == job["gt"] == str(result / "ground_truth.ply")
    assert (result / "ground_truth.ply").stat().st_size > 0
    html = (result / "report.html").read_text()
    assert str(result / "ground_truth.ply") in html and ".tmp-" not in html


def test_once_stopped_before_the_queue_drained_says_so_and_exits_130(tmp_path, monkeypatch, capsys):
    """`worker --once` ended by Ctrl-C or SIGTERM (its run returns with a job still queued): a script must be able to
    tell it from a drained queue."""
    import spadscan.worker.pool as pool
    from spadscan.worker.watcher import JobOptions, scan_once

    make_scan(tmp_path, "s")
    scan_once(tmp_path, Queue.for_root(tmp_path), JobOptions(), now=time.time() + SETTLE_S + 1)

    async def stopped_at_once(config):
        return pool.WorkerRun(settled={}, left={})

    monkeypatch.setattr(pool, "run_worker", stopped_at_once)
    assert cli_main(["worker", "--root", str(tmp_path), "--once"]) == 130
    assert "stopped with 1 job still queued or running" in capsys.readouterr().out
    q = Queue.for_root(tmp_path)
    q.finish(q.claim(), None)  # the queue drained: the exit status is a drained run's again
    assert cli_main(["worker", "--root", str(tmp_path), "--once"]) == 0
    assert "stopped" not in capsys.readouterr().out


def test_status_shows_a_live_job_following_its_scan_by_its_live_status(tmp_path, capsys):
    """A live job's log has no progress bar until its final run: while it follows the scan, --status (and the
    dashboard's queue table, which says the same) shows its live status."""
    from spadscan.dashboard.status import queue_status
    from spadscan.protocol.live_status import LiveStatus, status_path, write_status
    from spadscan.worker.jobs import Job

    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "l", "running")
    queue = Queue.for_root(root)
    queue.enqueue(Job(id="l-fast", scan="l", live=True))
    queue.claim()
    status_path(root / "l").parent.mkdir(parents=True)
    write_status(status_path(root / "l").parent, LiveStatus(views_used=24, views_published=29, steps=240,
                                                              job="l-fast"))
    assert cli_main(["worker", "--root", str(root), "--status"]) == 0
    (row,) = [line for line in capsys.readouterr().out.splitlines() if line.startswith("l-fast")]
    assert "live reconstruction" in row and "24/29 views, 240 steps" in row, row
    (job,) = queue_status(queue.path, root)["jobs"]
    assert "24/29 views, 240 steps" in job["detail"]


def fed_recon(capture, out, **options):
    """A stand-in reconstruction that draws the progress bars a test feeds it, `$FEED/<n>.bar` for n = 0, 1, ...
    in turn, until the test writes `$FEED/end`."""
    feed, n = Path(os.environ["FEED"]), 0
    while not (feed / "end").exists():
        bar = feed / f"{n}.bar"
        if bar.exists():
            print(bar.read_text(), end="\r", file=sys.stderr, flush=True)
            n += 1
        else:
            time.sleep(0.02)
    report = {"chamfer_mm": 1.5, "capture": str(capture)}
    (Path(out) / "report.json").write_text(json.dumps(report))
    return report


class Said:
    """A worker's log: each line with the time.monotonic() it was said; `wait_for` returns once a line matches."""

    def __init__(self):
        self.lines: list[tuple[float, str]] = []
        self.loop = asyncio.get_running_loop()
        self.changed = asyncio.Event()

    def __call__(self, line: str) -> None:  # also called from the worker's threads
        self.lines.append((time.monotonic(), line))
        self.loop.call_soon_threadsafe(self.changed.set)

    async def wait_for(self, predicate, times: int = 1) -> str:
        """The last line that matches, once `times` lines have."""
        while True:
            self.changed.clear()
            found = [line for _, line in self.lines if predicate(line)]
            if len(found) >= times:
                return found[-1]
            await self.changed.wait()


@pytest.mark.usefixtures("recon_stand_ins")
def test_the_worker_says_a_running_jobs_progress_in_its_own_terminal(tmp_path, arun, monkeypatch):
    """Between a job's 'started' and 'done' lines the worker says how far the job has got: its progress bar against
    its budget, at once when the job's stage changes (its training starts, its training ends) and every
    `progress_s` seconds in between, one line per job and never two within `progress_s` for the same stage."""
    from spadscan.worker.job_progress import AFTER_TRAINING
    from spadscan.worker.watcher import JobOptions

    root, feed = tmp_path / "captures", tmp_path / "feed"
    root.mkdir()
    feed.mkdir()
    make_scan(root, "a")
    monkeypatch.setenv("FEED", str(feed))
    every_s = 1.0

    def feed_bar(n: int, bar: str) -> None:
        (feed / "bar.tmp").write_text(bar)
        (feed / "bar.tmp").rename(feed / f"{n}.bar")  # whole, never half written

    async def scenario():
        said = Said()
        config = WorkerConfig(root=root, once=True, poll_s=0.05, recon="test_worker_process:fed_recon",
                              options=JobOptions(budget_s=20.0))
        worker = asyncio.create_task(Worker(config, log=said, progress_s=every_s).run())
        await said.wait_for(lambda line: line.startswith("a-fast started"))
        feed_bar(0, "reconstruct (fast):  57%|#####     | 4/7 s [00:04<00:03, step=38, loss=851]")
        first = await said.wait_for(lambda line: "step 38" in line)
        again = await said.wait_for(lambda line: "step 38" in line, times=2)  # the same stage, `every_s` later
        feed_bar(1, "reconstruct (fast): 100%|##########| 7/7 s [00:07<00:00, step=67, loss=518]")
        done = await said.wait_for(lambda line: AFTER_TRAINING in line)
        (feed / "end").write_text("")
        return await worker, said.lines, (first, again, done)

    settled, lines, (first, again, done) = arun(scenario(), timeout_s=60)
    assert settled == {"a-fast": "done"}
    assert first.startswith("a-fast at ") and " %: reconstruct (fast): 4/7 s, step 38, loss 851 [" in first, first
    assert "of the job's 00:20 budget" in first and "of the job's 00:20 budget" in again
    assert done.startswith("a-fast at ") and "7/7 s, step 67" in done, done
    progress = [(t, line) for t, line in lines if line.startswith("a-fast") and "started" not in line
                and " done in " not in line]
    assert all(line.startswith(("a-fast at ", "a-fast: setting up")) for _, line in progress), progress
    stages = [("setting up" if "setting up" in line else AFTER_TRAINING if AFTER_TRAINING in line else "training", t)
              for t, line in progress]
    for (stage, t), (next_stage, next_t) in zip(stages, stages[1:]):
        # (timed as said: a line may reach the log a little later than the look that chose it, never 0.5 s)
        assert next_stage != stage or next_t - t >= every_s / 2, f"two lines within {every_s} s: {progress}"
    assert [s for s, _ in stages].count(AFTER_TRAINING) >= 1 and stages[-1][0] == AFTER_TRAINING


def test_a_job_whose_capture_folder_is_gone_fails_without_making_it_again(tmp_path, arun):
    """Its scan moved or removed while the job waited: the result folder was made with its parents, and the removed
    capture came back as an empty folder (a scan moved back then landed inside it)."""
    from spadscan.worker.jobs import Job, job_id_for

    root = tmp_path / "captures"
    root.mkdir()
    Queue.for_root(root).enqueue(Job(id=job_id_for("gone", "fast"), scan="gone"))
    lines = []
    config = WorkerConfig(root=root, once=True, poll_s=0.1, recon=RECON)
    assert arun(Worker(config, log=lines.append).run(), timeout_s=120) == {"gone-fast": "failed"}
    assert not (root / "gone").exists()
    said = next(line for line in lines if line.startswith("gone-fast failed"))
    assert said == f"gone-fast failed: cannot prepare the result folder: its capture folder {root / 'gone'} is gone " \
                   f"(moved or removed)", said
