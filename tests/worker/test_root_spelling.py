"""Workers that spell the captures root differently (relative to their working directories, or absolute; the shared
filesystem mounted elsewhere) agree on which results their queue's claims produced: the completion marker names the
queue by its resolved path, and a marker that earlier versions wrote with a relative one is still read as this
queue's."""

from __future__ import annotations

import json
import os

from spadscan.worker import publishing
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import COMPLETE, Job, completion, mark_complete, result_path, scratch_path
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from test_publishing import _gone_pid
from test_watcher import make_scan

JOB = "s-fast"


def _gone() -> Holder:
    return Holder(**{**Holder.current().to_dict(), "pid": _gone_pid(), "pid_start": ""})


def _published_by_a_dead_worker(root) -> tuple[Queue, object]:
    """A worker run with `--root captures` (relative) published its job's result and died before recording it."""
    queue = Queue.for_root(root)
    queue.enqueue(Job(id=JOB, scan="s"))
    claim = queue.claim(_gone())
    scratch = scratch_path(claim.job, root, claim.token)
    scratch.mkdir(parents=True)
    (scratch / "mesh.ply").write_text("the job's mesh")
    (scratch / "report.json").write_text("{}")
    mark_complete(scratch, JOB, claim.token, queue.path)
    final = result_path(claim.job, root)
    queue.record_result(claim, str(final))
    os.rename(scratch, final)
    return queue, claim


def test_a_worker_with_the_absolute_root_records_the_job_a_relative_one_published_as_done_not_kept(
        tmp_path, monkeypatch, arun):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "captures").mkdir()
    make_scan(tmp_path / "captures", "s")
    _, claim = _published_by_a_dead_worker(os.path.relpath(tmp_path / "captures"))
    final = tmp_path / "captures" / "s" / "recon" / JOB
    assert completion(final)["queue"] == str(tmp_path / "captures" / ".queue"), "the marker names the queue whole"
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=tmp_path / "captures", once=True, poll_s=0.05), log=lines.append)
    settled = arun(worker.run(), timeout_s=60)
    assert not any("not run" in line for line in lines), lines
    assert any(f"its result {final} was in place" in line for line in lines), lines
    (row,) = worker.queue.statuses()
    assert (row.state, row.attempts, row.kept, row.result) == ("done", 1, False, str(final))
    assert worker.queue.record(JOB, claim.token)["outcome"] == "lost"
    assert "died mid-job" not in str(worker.queue.record(JOB, claim.token).get("error")), "it died after publishing"
    assert settled == {}, "nothing ran"


def test_an_older_marker_with_a_relative_queue_path_is_read_as_this_queues(tmp_path, monkeypatch):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    queue, claim = _published_by_a_dead_worker(root)
    final = result_path(claim.job, root)
    (final / COMPLETE).write_text(json.dumps({"job": JOB, "token": claim.token, "queue": "captures/.queue"}))
    monkeypatch.chdir(tmp_path / "captures" / "s")  # a worker started elsewhere than the one that wrote it
    assert publishing.own_result(Queue(root / ".queue"), JOB, final) is not None
    (final / COMPLETE).write_text(json.dumps({"job": JOB, "token": claim.token, "queue": "../other/.queue"}))
    assert publishing.own_result(queue, JOB, final) is None, "another queue's name"


def test_a_marker_naming_another_existing_queue_is_not_this_queues(tmp_path):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    queue, claim = _published_by_a_dead_worker(root)
    final = result_path(claim.job, root)
    other = Queue(tmp_path / "other")
    for marked, own in ((other.path, False), (tmp_path / "elsewhere" / ".queue", True),
                        (tmp_path / "captures" / "s" / ".." / ".queue", True)):
        (final / COMPLETE).write_text(json.dumps({"job": JOB, "token": claim.token, "queue": str(marked)}))
        assert (publishing.own_result(queue, JOB, final) is not None) == own, marked
    assert publishing.own_result(other, JOB, final) is None, "its claim token is no record of that queue's"


def test_a_left_result_is_published_by_a_worker_that_spells_the_root_otherwise(tmp_path, monkeypatch):
    """A finished result a stopped worker (`--root captures`) left unpublished: a worker given the absolute root
    publishes it instead of reconstructing the job again."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "captures").mkdir()
    make_scan(tmp_path / "captures", "s")
    relative = Queue.for_root("captures")
    relative.enqueue(Job(id=JOB, scan="s"))
    gone = relative.claim(_gone())
    scratch = scratch_path(gone.job, "captures", gone.token)
    scratch.mkdir(parents=True)
    (scratch / "mesh.ply").write_text("the finished mesh")
    mark_complete(scratch, JOB, gone.token, relative.path)
    assert relative.release(gone, "worker stopped before it could publish the result")
    absolute = Queue.for_root(tmp_path / "captures")
    held = absolute.claim()
    assert publishing.left_result(absolute, held, tmp_path / "captures") == tmp_path / scratch
