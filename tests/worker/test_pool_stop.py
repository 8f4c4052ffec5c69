"""A stopping worker gives every job it runs back to the queue, as it gives back any other job it holds
(`Worker._give_back`): a full disk that keeps out the attempt records (a rename needs no room, a record does) never
leaves the jobs after the first one held, their scratch folders behind, nor ends the worker on an error."""

from __future__ import annotations

import asyncio
import errno
from types import SimpleNamespace

from spadscan.worker.jobs import Job
from spadscan.worker.pool import Worker
from spadscan.worker.worker_config import WorkerConfig

JOBS = ("a-fast", "b-fast")


def running(worker: Worker, tmp_path) -> None:
    """Two claimed jobs whose processes have ended, each with its outcome file and scratch folder."""
    ended = asyncio.get_running_loop().create_future()
    ended.set_result(0)
    for job_id in JOBS:
        worker.queue.enqueue(Job(id=job_id, scan=job_id.split("-")[0]))
        claim = worker.queue.claim()
        scratch = tmp_path / f"scratch-{job_id}"
        scratch.mkdir()
        outcome = tmp_path / f"outcome-{job_id}.json"
        outcome.write_text("{}")
        worker.children[job_id] = SimpleNamespace(claim=claim, proc=SimpleNamespace(returncode=0, pid=None),
                                                  scratch=scratch, outcome=outcome, wait=ended)


def disk_full(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_a_worker_stopping_on_a_full_disk_gives_every_job_back(tmp_path, monkeypatch, arun):
    lines: list[str] = []
    (tmp_path / "captures").mkdir()
    worker = Worker(WorkerConfig(root=tmp_path / "captures", stop_grace_s=1), log=lines.append)

    async def stop() -> None:
        running(worker, tmp_path)
        monkeypatch.setattr(worker.queue, "_write_record", disk_full)
        await worker._stop_children()

    arun(stop())
    assert {job_id: worker.queue.job_paths()[job_id][0] for job_id in JOBS} == dict.fromkeys(JOBS, "queued")
    assert [line for line in lines if "back in the queue" in line] == [f"{j} stopped; back in the queue" for j in JOBS]
    assert not list(tmp_path.glob("scratch-*")) and not list(tmp_path.glob("outcome-*"))
    assert worker.children == {}
