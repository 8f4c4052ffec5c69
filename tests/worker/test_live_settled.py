"""A live job's status (`<scan>/recon/live/status.json`) ends 'done' with its result, or 'stopped' with the error, on
every path that settles the job: also when its worker died while publishing and another worker settles it
(publishing.reconcile, `Worker._keep`), and when the queue gives up on it because its worker died on its last attempt
(`reclaim_expired`). Such a job counts as failed for the worker that gave up on it (`--once`'s exit status).

The states a dead worker leaves are made here directly: a claim whose holder is a process that has exited."""

from __future__ import annotations

import dataclasses
import json
import os

import pytest

from spadscan.cli import main as cli_main
from spadscan.protocol.live_status import LiveStatus, read_status, status_path, write_status
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job, mark_complete, result_path, scratch_path
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from test_publishing import _gone_pid
from test_watcher import make_scan

JOB = "s-fast"
FINISHING = LiveStatus(views_used=2, views_published=2, steps=9, converged=False, state="final",
                       updated_utc="2026-11-27T17:04:05.715+00:00", views_planned=2, job=JOB)


@pytest.fixture
def root(tmp_path):
    """A complete scan `s` whose live job's status says finishing (the job wrote 'final' before its final run)."""
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    (root / "s" / "recon" / "live").mkdir(parents=True)
    write_status(root / "s" / "recon" / "live", FINISHING)
    return root


def _dead_claim(queue: Queue):
    """The live job claimed by a worker process that has exited since."""
    queue.enqueue(Job(id=JOB, scan="s", live=True))
    return queue.claim(Holder(**{**Holder.current().to_dict(), "pid": _gone_pid(), "pid_start": ""}))


def _finished(queue: Queue, root, step: str) -> None:
    """What a worker killed at publishing step `step` left of its live job's finished result."""
    claim = _dead_claim(queue)
    scratch = scratch_path(claim.job, root, claim.token)
    scratch.mkdir(parents=True)
    (scratch / "mesh.ply").write_text("the final mesh")
    (scratch / "report.json").write_text(json.dumps({"steps": 40, "converged": True, "scene": {"views": 2}}))
    mark_complete(scratch, JOB, claim.token, queue.path)
    if step == "marked-complete":
        return
    final = result_path(claim.job, root)
    queue.record_result(claim, str(final))
    os.rename(scratch, final)
    if step == "published, taken over":
        assert queue.reclaim_expired() == [(JOB, "queued")]
    elif step == "finished":
        assert queue.finish(claim, str(final))


def _run_once(root, arun, max_attempts: int = 3) -> tuple[dict, list[str]]:
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05, max_attempts=max_attempts), log=lines.append)
    return arun(worker.run(), timeout_s=60), lines


def _live(root) -> LiveStatus:
    return read_status(status_path(root / "s"))


@pytest.mark.parametrize("step", ["marked-complete", "published", "published, taken over", "finished"])
def test_a_live_job_settled_by_the_next_worker_says_done_with_its_result(root, arun, step):
    queue = Queue.for_root(root)
    _finished(queue, root, step)
    settled, lines = _run_once(root, arun)
    final = root / "s" / "recon" / JOB
    assert queue.job_paths()[JOB][0] == "done" and (final / "mesh.ply").read_text() == "the final mesh", lines
    status = _live(root)
    assert (status.state, status.result) == ("done", str(final)), (step, lines)
    assert (status.steps, status.converged) == (FINISHING.steps + 40, True), "the final result's figures"
    assert not any("not run" in line for line in lines), lines


def test_a_done_live_job_whose_status_says_done_is_left_alone_at_the_next_start(root, arun):
    queue = Queue.for_root(root)
    _finished(queue, root, "finished")
    said = dataclasses.replace(FINISHING, state="done", result="as the worker said it",
                               updated_utc="2026-11-27T17:05:00.000+00:00")
    write_status(root / "s" / "recon" / "live", said)
    _run_once(root, arun)
    assert _live(root) == said


def test_the_result_a_dead_worker_left_of_a_job_the_queue_gave_up_on_is_published_and_said_done(root, arun):
    """max-attempts 1: the worker that finds the dead claim gives the job up (failed), then publishes the complete
    result that claim left: the job is done, its status says so, and it does not count as failed."""
    _finished(Queue.for_root(root), root, "marked-complete")
    settled, lines = _run_once(root, arun, max_attempts=1)
    assert Queue.for_root(root).job_paths()[JOB][0] == "done", lines
    assert _live(root).state == "done"
    assert settled.get(JOB) != "failed", lines


def test_a_live_job_whose_worker_died_on_its_last_attempt_says_stopped_and_counts_as_failed(root, arun):
    queue = Queue.for_root(root, max_attempts=1)
    _dead_claim(queue)
    settled, lines = _run_once(root, arun, max_attempts=1)
    assert settled == {JOB: "failed"}, lines
    assert queue.job_paths()[JOB][0] == "failed"
    status = _live(root)
    assert status.state == "stopped" and "died mid-job" in status.note and "giving up" in status.note, status.note
    assert status.steps == FINISHING.steps, "the rest of the status stays as the job left it"


def test_worker_once_exits_1_after_giving_up_on_a_job_whose_worker_died(root, capsys):
    queue = Queue.for_root(root, max_attempts=1)
    queue.enqueue(Job(id=JOB, scan="s"))
    queue.claim(Holder(**{**Holder.current().to_dict(), "pid": _gone_pid(), "pid_start": ""}))
    assert cli_main(["worker", "--root", str(root), "--once", "--max-attempts", "1", "--poll-s", "0.05"]) == 1
    out = capsys.readouterr().out
    assert f"0 done, 1 failed ({JOB})" in out, out
