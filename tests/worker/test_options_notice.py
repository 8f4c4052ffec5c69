"""A worker given job options names every job that will run with other options (a job keeps the options it was
queued with): the jobs queued when it starts, and the jobs it queues again itself once it has started: a done job
whose result is gone, a dead worker's job it takes over."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.watcher import JobOptions, scan_once
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan

RECON = "test_worker_process:options_recon"  # writes the steps it was given into report.json
NOTICE = "keep the options they were queued with"
pytestmark = pytest.mark.usefixtures("recon_stand_ins")  # the job processes import options_recon


def run_once(root: Path, arun, steps: int) -> list[str]:
    """A worker run with `--once --steps steps` (the only option given); its log lines."""
    lines: list[str] = []
    config = WorkerConfig(root=root, once=True, poll_s=0.1, recon=RECON, options=JobOptions(steps=steps),
                          options_given=("steps",))
    arun(Worker(config, log=lines.append).run(), timeout_s=120)
    return lines


def steps_run(root: Path, scan: str) -> int | None:
    """The steps the job of `scan` ran with, as its result's report says."""
    return json.loads((root / scan / "recon" / f"{scan}-fast" / "report.json").read_text())["steps"]


def named(lines: list[str]) -> str:
    """Every notice line, joined: the jobs named as keeping their own options."""
    return "\n".join(line for line in lines if NOTICE in line)


def _gone_pid() -> int:
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    return gone.pid


def test_a_done_job_queued_again_for_its_missing_result_is_named(tmp_path, arun):
    make_scan(tmp_path, "t2")
    run_once(tmp_path, arun, steps=200)
    shutil.rmtree(tmp_path / "t2" / "recon" / "t2-fast")  # removed by hand: queued again when a worker starts
    make_scan(tmp_path, "t1")
    scan_once(tmp_path, Queue.for_root(tmp_path), JobOptions(steps=200))  # queued by an earlier worker
    lines = run_once(tmp_path, arun, steps=3)
    assert any("t2-fast: done, but its result" in line and "queued again" in line for line in lines), lines
    assert steps_run(tmp_path, "t1") == steps_run(tmp_path, "t2") == 200, "both ran with the options they had"
    notice = named(lines)
    assert "not steps 3" in notice and "t1-fast (steps 200)" in notice and "t2-fast (steps 200)" in notice, lines


def test_a_dead_workers_job_taken_over_is_named(tmp_path, arun):
    make_scan(tmp_path, "d")
    queue = Queue.for_root(tmp_path)
    queue.enqueue(Job(id="d-fast", scan="d", steps=200))
    gone = Holder(**{**Holder.current().to_dict(), "pid": _gone_pid(), "pid_start": ""})
    assert queue.claim(gone) is not None
    lines = run_once(tmp_path, arun, steps=3)
    said = f"d-fast: worker {gone.host} pid {gone.pid} died mid-job; queued again"
    assert any(said in line for line in lines), lines
    assert steps_run(tmp_path, "d") == 200
    assert "d-fast (steps 200)" in named(lines), lines


def test_each_job_is_named_once_and_jobs_with_the_options_given_are_not(tmp_path, arun):
    make_scan(tmp_path, "t2")
    run_once(tmp_path, arun, steps=200)
    shutil.rmtree(tmp_path / "t2" / "recon" / "t2-fast")
    make_scan(tmp_path, "t1")
    scan_once(tmp_path, Queue.for_root(tmp_path), JobOptions(steps=200))
    make_scan(tmp_path, "t3")  # queued by this worker, with its own options
    lines = run_once(tmp_path, arun, steps=3)
    notice = named(lines)
    assert notice.count("t1-fast") == 1 and notice.count("t2-fast") == 1 and "t3-fast" not in notice, lines
    assert steps_run(tmp_path, "t3") == 3
