"""A live job whose worker died is taken over by another worker and queued again: its live status says so ('queued',
with why), as on every other path that gives a job back, and says it while the taking-over worker still holds the
job, so that the note never stands over the first status of the attempt that claims it next."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from dataclasses import replace

import pytest

from spadscan.protocol.errors import CaptureError
from spadscan.protocol.live_status import LiveStatus, read_status, status_path, write_status
from spadscan.worker.holder import Holder, holder_gone
from spadscan.worker.jobs import Job
from spadscan.worker.pool import Worker
from spadscan.worker.worker_config import WorkerConfig

JOB = "s-fast"
FOLLOWING = LiveStatus(views_used=38, views_published=60, steps=563, state="live", chamfer_mm=68.6505,
                       updated_utc="2026-12-03T13:17:00.000+00:00", views_planned=60, job=JOB)
"""The last status the dead worker's attempt wrote: following the scan."""


def dead_holder() -> Holder:
    """A worker process of this machine that has exited (test_queue's dead holder)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    dead = replace(Holder.current(), pid=proc.pid, pid_start="")
    assert holder_gone(dead.to_dict())
    return dead


def live_state(root) -> str | None:
    try:
        return read_status(status_path(root / "s")).state
    except CaptureError:
        return None


@pytest.fixture
def abandoned(tmp_path):
    """A worker (in this process) beside a live job of scan `s` held by a worker that died mid-job."""
    root = tmp_path / "captures"
    (root / "s" / "recon" / "live").mkdir(parents=True)
    write_status(root / "s" / "recon" / "live", FOLLOWING)
    worker = Worker(WorkerConfig(root=root, max_attempts=3), log=lambda line: None)
    worker.queue.enqueue(Job(id=JOB, scan="s", live=True, device="cpu"))
    assert worker.queue.claim(dead_holder()) is not None
    return worker


def status_as_it_goes_back(monkeypatch, worker) -> list[str | None]:
    """The live status's state each time the queue moves the job to queued/, read just before the move."""
    settle = worker.queue._settle
    seen: list[str | None] = []

    def watched(src, job_id, state):
        if state == "queued":
            seen.append(live_state(worker.root))
        return settle(src, job_id, state)

    monkeypatch.setattr(worker.queue, "_settle", watched)
    return seen


def test_a_dead_workers_live_job_says_queued_again_before_it_goes_back(abandoned, monkeypatch, arun):
    lines: list[str] = []
    abandoned.log = lines.append
    at_requeue = status_as_it_goes_back(monkeypatch, abandoned)

    arun(abandoned._take_over())
    assert abandoned.queue.job_paths()[JOB][0] == "queued"
    dead = abandoned.queue.records(JOB)[0]
    assert f"{JOB}: worker {dead['host']} pid {dead['pid']} died mid-job; queued again" in lines, lines
    assert at_requeue == ["queued"], "said while the job was still held"
    status = read_status(status_path(abandoned.root / "s"))
    assert "died mid-job" in status.note and "back in the queue" in status.note, status.note
    kept = dataclasses.replace(status, state="live", note=None, updated_utc="", figures_utc=None)
    assert kept == dataclasses.replace(FOLLOWING, updated_utc=""), "its figures stay: the stopped attempt's"
    assert status.figures_utc == FOLLOWING.updated_utc, "and say when they were measured"


def test_a_dead_workers_job_on_its_last_attempt_never_says_queued(abandoned, monkeypatch, arun):
    abandoned.queue.max_attempts = 1
    at_requeue = status_as_it_goes_back(monkeypatch, abandoned)
    arun(abandoned._take_over())
    assert abandoned.queue.job_paths()[JOB][0] == "failed"
    assert at_requeue == [] and live_state(abandoned.root) == "stopped"
