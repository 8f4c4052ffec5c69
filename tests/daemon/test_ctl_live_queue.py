"""`spadscan ctl status` and `ctl wait` say when the scan's live reconstruction waits in the worker's queue behind
another job (a worker runs as many jobs at once as its --processes), in the dashboard's words: what it waits for
(the jobs it is behind, by name), or that a worker takes it at its next look, or that no worker is running. The
queue's files are the worker's own: written by its Queue and presence code, as a worker with two jobs leaves them."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest

from spadscan.cli import main
from spadscan.commands.ctl import PauseNotes, ProgressBar, live_line, live_status
from spadscan.protocol.live_status import LiveStatus, write_status
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job
from spadscan.worker.live.done import mark_live_queued
from spadscan.worker.presence import Presence, write_presence
from spadscan.worker.queue import Queue

from status_daemon import StatusDaemon

ELSEWHERE = Holder("gpu-box", 4242)  # a worker on another machine: judged by its lease alone
BEHIND_Q1 = "waiting for q1-fast to finish (the worker runs 1 job at a time; `--processes 2` runs 2)"


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def running_job(root: Path, job_id: str, holder: Holder) -> None:
    """`job_id` (of scan `q1` ...: the id's first part) queued and claimed by `holder`: a worker at its job."""
    queue = Queue.for_root(root)
    queue.enqueue(Job(id=job_id, scan=job_id.rsplit("-", 1)[0]))
    claim = queue.claim(holder)
    assert claim is not None and claim.job.id == job_id


def worker_present(root: Path, holder: Holder, processes: int, running: tuple = ()) -> None:
    write_presence(Queue.for_root(root).path, Presence(holder.to_dict(), str(root), time.time(), processes,
                                                       running=list(running), token=f"{holder.pid:08x}"))


def status_of(root: Path, scan: str = "mug") -> dict:
    """The daemon's status while it records `scan` under captures root `root` (what `ctl` reads the queue by)."""
    return {"state": "scanning", "scan": scan, "path": str(root / scan), "pose": 3, "poses": 6, "progress": "3/6",
            "reason": None, "daemon": {"captures": str(root)}}


def captures(tmp_path: Path, running: dict, workers: list) -> Path:
    """A captures root whose workers (`workers`: (holder, job processes, jobs it runs) each) run the jobs `running`
    (job id: its holder) while the live job of scan mug, being recorded, waits in the queue."""
    root = tmp_path / "caps"
    (root / "mug").mkdir(parents=True)
    for job_id, holder in running.items():  # claimed before mug's live job is queued: a claim takes that first
        running_job(root, job_id, holder)
    Queue.for_root(root).enqueue(Job(id="mug-fast", scan="mug", live=True))
    for holder, processes, jobs in workers:
        worker_present(root, holder, processes, running=jobs)
    return root


@pytest.fixture
def busy(tmp_path) -> Path:
    """One worker with one job process, at q1-fast (the final run of an earlier scan)."""
    return captures(tmp_path, {"q1-fast": Holder.current()}, [(Holder.current(), 1, ("q1-fast",))])


def ctl_status(root: Path, monkeypatch, capsys, *flags: str) -> tuple[dict, str]:
    import spadscan.daemon.client as client

    monkeypatch.setattr(client, "call", lambda path, op, timeout, **request: {"ok": True, **status_of(root)})
    assert main(["ctl", "--socket", str(root / "ctl.sock"), "status", *flags]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    return json.loads(out), out


def test_status_says_the_live_fit_is_queued_behind_the_job_that_runs(busy, monkeypatch, capsys):
    """Before: no `live` at all (the live job had written no status yet), so nothing said it waits."""
    me = Holder.current()
    for flags in ((), ("--json",)):
        shown, out = ctl_status(busy, monkeypatch, capsys, *flags)
        assert (out.count("\n") == 1) == bool(flags), "--json: one line; without it, indented"
        queued = shown["live"]["queued"]
        assert set(shown["live"]) == {"queued"}, "no live status yet: nothing else to say of the fit"
        assert queued["job"] == "mug-fast" and queued["behind"] == ["q1-fast"]
        assert queued["workers"] == [f"{me.host} pid {me.pid}"] and queued["processes"] == 1
        assert queued["said"] == BEHIND_Q1 and queued["waiting_s"] >= 0
    assert live_line(shown["live"]) == "live reconstruction queued: " + BEHIND_Q1


def test_a_live_job_given_back_to_the_queue_says_queued_again_and_what_it_waits_for(busy, monkeypatch, capsys):
    folder = busy / "mug" / "recon" / "live"
    folder.mkdir(parents=True)
    write_status(folder, LiveStatus(views_used=8, views_published=9, steps=40, job="mug-fast"))
    mark_live_queued(Job(id="mug-fast", scan="mug", live=True), busy, "its worker stopped", lambda line: None)
    shown, _ = ctl_status(busy, monkeypatch, capsys, "--json")
    live = shown["live"]
    assert live["state"] == "queued" and live["views_used"] == 8 and live["queued"]["behind"] == ["q1-fast"]
    line = live_line(live, 3)
    # the stopped attempt's figures, as of when they were measured: never the job's now
    assert line.startswith("live reconstruction queued again: the stopped attempt's 8/9 views, 40 steps (as of ") \
        and line.endswith(
        "; " + BEHIND_Q1), line
    # a status that could not be set to 'queued' (a full disk) still reads as following the scan: the queue says not
    line = live_line({**live, "state": "live"}, 3)
    assert line.startswith("live reconstruction following the scan: 8/9 views") and line.endswith(
        "; its job is queued: " + BEHIND_Q1), line


def test_a_free_job_process_or_no_worker_is_said_instead(busy):
    worker_present(busy, Holder.current(), 2, running=("q1-fast",))  # the same worker, now with a process free
    assert live_status(status_of(busy))["queued"]["said"] == "a worker takes it at its next look"
    for path in (Queue.for_root(busy).path / "workers").glob("*.json"):
        path.unlink()  # the worker stopped
    queued = live_status(status_of(busy))["queued"]
    assert queued["workers"] == [] and queued["said"] == (
        f"no worker is running: start one with `spadscan worker --root {busy.resolve()} --live`")


def test_two_workers_both_busy_are_named_with_the_way_to_run_one_job_more(tmp_path):
    me = Holder.current()
    root = captures(tmp_path, {"q1-fast": me, "q3-fast": ELSEWHERE, "q5-fast": ELSEWHERE},
                    [(me, 1, ("q1-fast",)), (ELSEWHERE, 2, ("q3-fast", "q5-fast"))])
    assert live_status(status_of(root))["queued"]["said"] == (
        "waiting for one of q1-fast, q3-fast, q5-fast to finish (the 2 workers run 3 jobs at a time; one more "
        f"worker, or `--processes 2` for the worker on {me.host} pid {me.pid}, runs 4)")


def test_a_job_whose_worker_stopped_renewing_its_claim_is_not_waited_for(busy):
    [running] = (Queue.for_root(busy).path / "running").glob("q1-fast~*.json")
    then = time.time() - 40  # a lease of 60 s: two renewals missed
    os.utime(running, (then, then))
    assert live_status(status_of(busy))["queued"]["said"] == "a worker takes it at its next look"


def dead_holder() -> Holder:
    """A process of this machine that has exited: a worker killed mid-job."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return replace(Holder.current(), pid=proc.pid, pid_start="")


def test_a_worker_that_died_is_neither_waited_for_nor_counted(tmp_path):
    """Its claim and its presence file are fresh: only its process, gone from this machine, says it is dead."""
    dead = dead_holder()
    root = captures(tmp_path, {"q1-fast": dead}, [(dead, 1, ("q1-fast",))])
    queued = live_status(status_of(root))["queued"]
    assert queued["behind"] == [] and queued["workers"] == []
    assert queued["said"].startswith("no worker is running: start one with `spadscan worker --root ")


def test_no_word_once_the_live_job_runs_nor_without_a_queue(busy, tmp_path):
    assert Queue.for_root(busy).claim().job.id == "mug-fast"  # a live job is claimed first
    assert live_status(status_of(busy)) is None, "claimed, no live status yet: as before"
    (tmp_path / "bare" / "mug").mkdir(parents=True)
    assert live_status(status_of(tmp_path / "bare")) is None


def test_wait_without_a_terminal_says_once_that_the_live_fit_is_queued_and_when_it_starts(busy):
    stream = io.StringIO()
    notes = PauseNotes("mug", stream)
    notes.update(status_of(busy))
    notes.update(status_of(busy))  # the same: no second line
    queue = Queue.for_root(busy)
    [q1] = (queue.path / "running").glob("q1-fast~*.json")
    os.rename(q1, queue.path / "done" / "q1-fast.json")  # q1's job ends; the worker claims mug's
    assert queue.claim().job.id == "mug-fast"
    (busy / "mug" / "recon" / "live").mkdir(parents=True)
    write_status(busy / "mug" / "recon" / "live", LiveStatus(views_used=0, views_published=3, steps=0,
                                                             state="waiting", job="mug-fast"))
    notes.update(status_of(busy))
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2 and lines[0] == "spadscan: scan 'mug' live reconstruction queued: " + BEHIND_Q1
    assert lines[1].startswith("spadscan: scan 'mug' live reconstruction waiting for views: 0/3 views"), lines


def test_wait_on_a_terminal_shows_the_queue_on_its_progress_bar(busy):
    stream = Terminal()
    bar = ProgressBar("mug", stream)
    try:
        bar.update(status_of(busy))
    finally:
        bar.close()
    assert "scanning; live reconstruction queued: " + BEHIND_Q1 in stream.getvalue()


def test_a_ctl_status_process_says_it_without_loading_torch(busy, sock_dir):
    """A real `ctl status` process, against a daemon on a socket, reads the queue with the worker's own queue code
    and stays quick to start (no torch: a second and more). The socket is in the short sock_dir: a long TMPDIR makes
    one under the captures root too long."""
    path = str(sock_dir / "ctl.sock")
    server = StatusDaemon(path, status_of(busy))
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.01})
    thread.start()
    try:
        r = subprocess.run([sys.executable, "-X", "importtime", "-m", "spadscan.cli", "ctl", "--socket", path,
                            "status", "--json"], capture_output=True, text=True, timeout=120)
    finally:
        server.shutdown()
        thread.join()
        server.server_close()
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["live"]["queued"]["said"] == BEHIND_Q1
    imported = {line.rsplit("|", 1)[1].strip().split(".")[0] for line in r.stderr.splitlines()
                if line.startswith("import time:") and line.count("|") == 2}
    assert "spadscan" in imported and "torch" not in imported, sorted(imported)


def test_a_live_fit_whose_worker_was_killed_says_so_not_that_it_follows_the_scan(tmp_path, monkeypatch, capsys):
    """A worker killed mid-scan leaves its live status saying 'live' for good; the queue knows its claim is dead (as
    `spadscan worker --status` says 'stale'), and `ctl status` says it too; not once the job has ended (its live
    status is written just after it leaves running/), nor while a worker renews its claim."""
    dead = dead_holder()
    root = tmp_path / "caps"
    folder = root / "mug" / "recon" / "live"
    folder.mkdir(parents=True)
    queue = Queue.for_root(root)
    queue.enqueue(Job(id="mug-fast", scan="mug", live=True))
    assert queue.claim(dead).job.id == "mug-fast"
    write_status(folder, LiveStatus(views_used=8, views_published=9, steps=40, job="mug-fast"))
    shown, _ = ctl_status(root, monkeypatch, capsys, "--json")
    assert shown["live"]["gone"].startswith("its job mug-fast is stale: "), shown["live"]
    line = live_line(shown["live"], 3)
    assert line.startswith("live reconstruction following the scan: 8/9 views") and "is stale: " in line, line
    [running] = (queue.path / "running").glob("mug-fast~*.json")
    os.rename(running, queue.path / "done" / "mug-fast.json")
    assert "gone" not in live_status(status_of(root)), "ended: its status is written just after"
    live = Holder.current()
    (queue.path / "done" / "mug-fast.json").rename(queue.path / "queued" / "mug-fast.json")
    assert queue.claim(live).job.id == "mug-fast"
    assert "gone" not in live_status(status_of(root)), "its worker renews the claim: it follows the scan"
