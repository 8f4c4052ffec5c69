"""A worker that takes over a job says why its holder was given up on, as `worker --status` says it: a holder whose
process is gone from this machine died mid-job; one elsewhere that went silent stopped renewing its lease."""

from __future__ import annotations

import os
import re
import time

from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job
from spadscan.worker.pool import Worker
from spadscan.worker.worker_config import WorkerConfig

from test_reclaim_note import dead_holder

JOB = "s-fast"


def holding_worker(tmp_path, holder: Holder) -> tuple[Worker, list[str]]:
    """A worker (in this process) beside job JOB, claimed by `holder`."""
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=tmp_path, lease_s=60.0), log=lines.append)
    worker.queue.enqueue(Job(id=JOB, scan="s"))
    assert worker.queue.claim(holder) is not None
    return worker, lines


def stale_why(worker: Worker) -> str:
    """Why --status shows the job stale (before its take-over)."""
    (row,) = worker.queue.statuses()
    assert row.shown_state == "stale", row
    return row.stale.partition("; the next worker")[0]


def test_a_job_whose_worker_was_killed_is_said_to_have_died(tmp_path, arun):
    dead = dead_holder()
    worker, lines = holding_worker(tmp_path, dead)
    why = stale_why(worker)
    assert why == f"worker {dead.host} pid {dead.pid} died mid-job"
    arun(worker._take_over())
    assert lines == [f"{JOB}: {why}; queued again"], lines
    assert not any("stopped" in line for line in lines)


def test_a_job_whose_worker_elsewhere_went_silent_is_said_to_have_stopped_renewing(tmp_path, arun):
    far = Holder("elsewhere", 4242, "another-boot", "pid:[1]", "1")
    worker, lines = holding_worker(tmp_path, far)
    (held,) = (tmp_path / ".queue" / "running").iterdir()
    old = time.time() - 120.0
    os.utime(held, (old, old))  # two minutes without a heartbeat: its 60 s lease has expired
    said = r"worker elsewhere pid 4242 stopped renewing its lease \(1[23]\d s > 60 s\)"
    assert re.fullmatch(said, stale_why(worker))
    arun(worker._take_over())
    assert len(lines) == 1 and re.fullmatch(f"{JOB}: {said}; queued again", lines[0]), lines


def test_a_dead_workers_job_on_its_last_attempt_is_said_to_have_failed(tmp_path, arun):
    dead = dead_holder()
    worker, lines = holding_worker(tmp_path, dead)
    worker.queue.max_attempts = 1
    arun(worker._take_over())
    assert lines == [f"{JOB}: worker {dead.host} pid {dead.pid} died mid-job; failed"], lines
    assert worker.settled == {JOB: "failed"}
