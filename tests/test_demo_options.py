"""`spadscan demo` refuses what the daemon or the worker would refuse before it starts anything, and when a child
fails anyway its error repeats the line of the child's log that says why. (The whole loop: tests/e2e/test_demo.py.)"""

from __future__ import annotations

import errno
import sys
from dataclasses import fields
from pathlib import Path

import pytest

import spadscan.demo as demo
from spadscan.cli import main
from spadscan.daemon.config import ScanConfig
from spadscan.demo import DemoError, DemoOptions, Processes, check_options, last_log_line, run_demo
from spadscan.protocol.errors import ConfigError

MOST_VIEWS = int(next(f.metadata["key"].hi for f in fields(ScanConfig) if f.name == "views"))


@pytest.fixture
def nothing_starts(monkeypatch):
    """Fail the test if the demo starts a process or a progress bar."""
    def start(self, name, argv, log):
        raise AssertionError(f"the demo started {name} although an option is refused")

    monkeypatch.setattr(Processes, "start", start)


BUDGET_RULE = "must be a number of seconds > 0 and at most 604800 (a week)"
NOT_FINITE = "--budget-s: time budget is not a finite number of seconds: it must be > 0 and at most 604800 (a week)"
"""The worker's rule for a time budget, as the demo says it."""


@pytest.mark.parametrize("changes, message", [
    ({"budget_s": 0.0}, f"--budget-s: time budget 0.0 s {BUDGET_RULE}"),
    ({"budget_s": -3.0}, f"--budget-s: time budget -3.0 s {BUDGET_RULE}"),
    ({"budget_s": float("inf")}, NOT_FINITE),
    ({"budget_s": float("nan")}, NOT_FINITE),
    ({"budget_s": 1e9}, f"--budget-s: time budget 1000000000.0 s {BUDGET_RULE}"),
    ({"budget_s": None}, "--budget-s: a time budget is needed"),
    ({"views": MOST_VIEWS + 1}, f"--views {MOST_VIEWS + 1} must be an integer in [4, {MOST_VIEWS}]"),
    ({"views": 3}, f"--views 3 must be an integer in [4, {MOST_VIEWS}]"),
    ({"scene": "teapot"}, "unknown scene 'teapot'"),
    ({"arm": "ur"}, "--arm 'ur' must be one of sim, ur-sim"),
    ({"sensor": "vl53l8"}, "--sensor 'vl53l8' must be one of"),
])
def test_refused_options_start_nothing(tmp_path, nothing_starts, changes, message):
    opts = DemoOptions(out=tmp_path / "demo", **changes)
    with pytest.raises(DemoError) as info:
        run_demo(opts, progress_factory=None)
    assert str(info.value).startswith(message) and "\n" not in str(info.value)
    assert not opts.out.exists(), "nothing is created for refused options"


def test_the_views_limit_is_the_daemons():
    check_options(DemoOptions(out=Path("x"), views=MOST_VIEWS))
    with pytest.raises(DemoError):
        check_options(DemoOptions(out=Path("x"), views=MOST_VIEWS + 1))


def test_an_out_that_is_a_file(tmp_path, nothing_starts):
    (tmp_path / "afile").write_text("x")
    with pytest.raises(DemoError, match="afile: exists and is not a folder"):
        run_demo(DemoOptions(out=tmp_path / "afile"), progress_factory=None)
    assert (tmp_path / "afile").read_text() == "x"


def test_the_rig_config_is_checked_as_the_daemon_would_before_it_starts(tmp_path, nothing_starts):
    # frames_per_pose is no command-line option; 0 stands for anything the daemon's config check refuses
    with pytest.raises(ConfigError, match=r"\[scan\] frames_per_pose = 0 is outside"):
        run_demo(DemoOptions(out=tmp_path / "demo", frames_per_pose=0), progress_factory=None)


@pytest.mark.parametrize("argv, message", [
    (["--views", "8", "--budget-s", "0"], f"--budget-s: time budget 0.0 s {BUDGET_RULE}"),
    (["--views", "20000"], f"--views 20000 must be an integer in [4, {MOST_VIEWS}]"),
])
def test_through_the_command_line(tmp_path, capsys, nothing_starts, argv, message):
    assert main(["demo", "--out", str(tmp_path / "d"), *argv]) == 1
    captured = capsys.readouterr()
    assert captured.err == f"spadscan: error: {message}\n", "one line, and no banner before it"
    assert not (tmp_path / "d").exists()


def test_an_out_it_may_not_write_is_refused_before_the_banner_names_its_logs(tmp_path, capsys, monkeypatch,
                                                                            nothing_starts):
    """The banner said "logs in OUT/logs" and then the demo refused OUT: a place that never came to be. The refusal
    is simulated at mkdir (EACCES), as root may write anywhere."""
    out = tmp_path / "ro" / "dm"
    mkdir = Path.mkdir

    def guarded_mkdir(self, *args, **kwargs):
        if self == out:
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", guarded_mkdir)
    assert main(["demo", "--out", str(out)]) == 1
    assert capsys.readouterr().err == f"spadscan: error: {out}: permission denied\n", "one line, and no banner"


# ---- a child that fails anyway -------------------------------------------------------------------------------------
def test_last_log_line_finds_the_reason(tmp_path):
    log = tmp_path / "worker.log"
    log.write_text("12:00:01 INFO queued demo-1\n"
                   "spadscan: error: --budget-s 0.0 must be > 0 seconds\n"
                   "fit:  40%|####      | 4/10 [00:01<00:02, 3.1step/s]\rfit: 100%|##########| 10/10 [00:03<00:00]\n"
                   "\n")
    assert last_log_line(log) == "--budget-s 0.0 must be > 0 seconds"
    log.write_text("Traceback (most recent call last):\n  File \"x.py\", line 1\nValueError: bad thing\n\n")
    assert last_log_line(log) == "ValueError: bad thing"
    log.write_text("")
    assert last_log_line(log) is None
    assert last_log_line(tmp_path / "missing.log") is None


def _child(message: str) -> list[str]:
    return [sys.executable, "-c", f"import sys; print({message!r}, file=sys.stderr); sys.exit(1)"]


def test_a_daemon_that_dies_at_start_up_says_why(tmp_path):
    procs = Processes()
    log = tmp_path / "logs" / "daemon.log"
    proc = procs.start("daemon", _child("spadscan: error: rig.toml: [scan] views = 20000 is outside [1, 10000]"), log)
    proc.wait(timeout=60)
    with pytest.raises(DemoError) as info:
        demo._wait_for_daemon(tmp_path / "no.sock", proc, log, timeout_s=30)
    assert str(info.value) == (f"the daemon exited with code 1 at start-up: rig.toml: [scan] views = 20000 is "
                               f"outside [1, 10000] (log: {log})")


@pytest.mark.parametrize("held, stuck", [("mug-for-paper", None), (None, "mug-for-paper")],
                         ids=["taken over", "could not be taken over"])
def test_a_scan_no_demo_run_started_is_never_aborted(tmp_path, monkeypatch, held, stuck):
    """A user's rig writing into the demo's captures folder left a scan unfinished: the demo's daemon finds it at
    start-up, and the demo refuses to go on, naming it, rather than abort it as an earlier demo run's."""
    asked = []

    def daemon(sock, op, **kwargs):
        asked.append(op)
        return {"ok": True, "scan": held, "pose": 7, "poses": 64,
                "cannot_take_over": None if stuck is None else {"scan": stuck}}

    monkeypatch.setattr(demo, "call", daemon)
    demo.record_started(tmp_path, "demo-20261204-190100")  # an earlier demo run's scan, finished
    with pytest.raises(DemoError, match=r"holds scan 'mug-for-paper', left unfinished, which no demo run started: "
                                        r"resume or abort it with the rig that recorded it"):
        demo._abort_earlier_scans(Path("d.sock"), tmp_path, tmp_path / "captures")
    assert asked == ["status"], "nothing aborted"


def test_a_scan_an_earlier_demo_run_started_is_aborted_and_said(tmp_path, monkeypatch):
    asked = []

    def daemon(sock, op, **kwargs):
        asked.append((op, kwargs.get("name")))
        return {"ok": True, "scan": "demo-20261204-190100", "pose": 72, "poses": 128} if op == "status" else {}

    monkeypatch.setattr(demo, "call", daemon)
    demo.record_started(tmp_path, "demo-20261204-190100")
    said = demo._abort_earlier_scans(Path("d.sock"), tmp_path, tmp_path / "captures")
    assert asked == [("status", None), ("abort", "demo-20261204-190100")]
    assert said == ["an earlier demo run was interrupted: its scan demo-20261204-190100 (72 of 128 poses) is kept "
                    "aborted; starting a new one"]


def test_only_its_own_daemon_answers_the_demo(tmp_path):
    """Another daemon serves the demo's socket (a demo still running into the same folder, or one killed a moment
    ago): the demo waits for its own daemon, which exits since the socket is taken, and says why; it never drives the
    other daemon's scans (it would abort them as an earlier run's)."""
    import json
    import os
    import socketserver
    import tempfile
    import threading

    folder = Path(tempfile.mkdtemp(prefix="spadscan-t-"))  # a Unix socket path must stay short
    sock, answered = folder / "d.sock", tmp_path / "answered"

    class Other(socketserver.StreamRequestHandler):
        def handle(self):
            self.rfile.readline()
            reply = {"ok": True, "state": "scanning", "scan": "other", "daemon": {"pid": os.getpid()}}
            self.wfile.write((json.dumps(reply) + "\n").encode())
            answered.touch()

    server = socketserver.UnixStreamServer(str(sock), Other)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    # The demo's own daemon: it exits, as a daemon does when another one listens on its socket, once the other one
    # has answered the demo (so the demo had the chance to take that answer for its own daemon's).
    own = [sys.executable, "-c", f"import os, sys, time\n"
                                 f"while not os.path.exists({str(answered)!r}): time.sleep(0.02)\n"
                                 f"sys.exit('spadscan: error: another daemon is already listening')"]
    procs = Processes()
    log = tmp_path / "daemon.log"
    try:
        proc = procs.start("daemon", own, log)
        with pytest.raises(DemoError) as info:
            demo._wait_for_daemon(sock, proc, log, timeout_s=60)
        assert str(info.value) == (f"the daemon exited with code 1 at start-up: another daemon is already listening "
                                   f"(log: {log})")
    finally:
        procs.stop_all()
        server.shutdown()
        server.server_close()
        sock.unlink(missing_ok=True)
        folder.rmdir()


def test_a_worker_that_fails_says_why(tmp_path, monkeypatch):
    monkeypatch.setattr(demo, "_spadscan", lambda *args: _child("spadscan: error: capture x: no measurements"))
    procs = Processes()
    with pytest.raises(DemoError) as info:
        demo._reconstruct(DemoOptions(out=tmp_path, budget_s=5), tmp_path / "captures", "scan", procs,
                          tmp_path / "logs")
    log = tmp_path / "logs" / "worker.log"
    assert str(info.value) == f"the worker exited with code 1: capture x: no measurements (log: {log})"
    procs.stop_all()


def test_a_worker_that_fails_another_job_than_the_demos_is_no_failure_of_the_demo(tmp_path, monkeypatch):
    """A rerun after an interrupted live demo: the earlier run's live job of the scan the rerun aborted ends failed,
    and `spadscan worker --once` exits 1, though the demo's own scan was reconstructed."""
    from spadscan.worker.jobs import Job
    from spadscan.worker.queue import Queue

    queue = Queue.for_root(tmp_path / "captures")
    queue.enqueue(Job(id="scan-fast", scan="scan"))
    queue.finish(queue.claim())
    monkeypatch.setattr(demo, "_spadscan", lambda *args: _child("spadscan worker: 1 done, 1 failed (old-fast)"))
    procs = Processes()
    demo._reconstruct(DemoOptions(out=tmp_path, budget_s=5), tmp_path / "captures", "scan", procs, tmp_path / "logs")
    procs.stop_all()


def test_a_silent_failure_still_names_the_log(tmp_path):
    procs = Processes()
    log = tmp_path / "daemon.log"
    proc = procs.start("daemon", [sys.executable, "-c", "raise SystemExit(3)"], log)
    proc.wait(timeout=60)
    with pytest.raises(DemoError) as info:
        demo._wait_for_daemon(tmp_path / "no.sock", proc, log, timeout_s=30)
    assert str(info.value) == f"the daemon exited with code 3 at start-up (log: {log})"


def test_the_demo_reads_its_own_report_not_one_moved_aside(tmp_path):
    import os

    from spadscan.demo import _find_report

    recon = tmp_path / "scan" / "recon"
    with pytest.raises(DemoError, match="wrote no report"):
        _find_report(tmp_path / "scan")
    current, aside = recon / "scan-fast", recon / "scan-fast.replaced-20261125T200000Z-ab12"
    for folder in (current, aside):
        folder.mkdir(parents=True)
        (folder / "report.json").write_text("{}")
    os.utime(current / "report.json", (1_000, 1_000))  # the folder moved aside is the newer file
    assert _find_report(tmp_path / "scan") == current / "report.json"


def test_a_line_the_demo_says_while_a_bar_runs_starts_a_line_of_its_own(monkeypatch, tmp_path, capsys):
    """The live job's state changes are said while the scan's bar is drawn: above the bar, never glued to its end."""
    def fake_run_demo(opts, bar, say):
        progress = bar(10, "scan (poses)", "pose")
        progress.update(3)
        say("live reconstruction following the scan: 3/3 views, 10 steps")
        progress.update(7)
        progress.close()
        say("live reconstruction done: 10/10 views, 40 steps, Chamfer 1.21 mm")
        return {"mesh": str(tmp_path / "mesh.ply"), "warnings": [], "converged": True, "pictures": [], "live": None,
                "chamfer_mm": 1.21, "seconds": {"start_s": 0.1, "scan_s": 1.0, "reconstruct_s": 2.0, "total_s": 3.1},
                "preset": "fast", "report_html": str(tmp_path / "report.html"), "dashboard": None}

    monkeypatch.setattr(demo, "run_demo", fake_run_demo)
    assert main(["demo", "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    said = [line for line in err.split("\n")
            if "live reconstruction following" in line or "live reconstruction done" in line]
    assert len(said) == 2, err
    assert all(line.split("\r")[-1].startswith("live reconstruction") for line in said), said


def test_a_demo_whose_run_did_not_converge_says_what_ended_it_and_what_gives_it_longer(monkeypatch, tmp_path, capsys):
    # As its report.json says it, among the run's warnings (end_of_run.unconverged_line: what ended it and the flag
    # that gives it longer, the demo's own --budget-s): the same line as summary.json, the page and the dashboard.
    from spadscan.worker.end_of_run import unconverged_line

    def fake_run_demo(opts, bar, say):
        return {"mesh": str(tmp_path / "mesh.ply"), "warnings": [unconverged_line("budget")], "converged": False,
                "pictures": [], "live": None,
                "chamfer_mm": 1.12, "seconds": {"start_s": 0.1, "scan_s": 1.0, "reconstruct_s": 2.0, "total_s": 3.1},
                "preset": "fast", "report_html": str(tmp_path / "report.html"), "dashboard": None}

    monkeypatch.setattr(demo, "run_demo", fake_run_demo)
    assert main(["demo", "--out", str(tmp_path / "out"), "--budget-s", "90"]) == 0
    said = [line for line in capsys.readouterr().out.splitlines() if line.startswith("warning:")]
    assert said == ["warning:  the run did not converge: its mesh may still be changing (it ended on its time budget: "
                    "a larger --budget-s gives it longer)"], said
