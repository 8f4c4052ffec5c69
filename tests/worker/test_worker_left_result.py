"""A finished result a stopped worker could not publish (a full disk) is published by whichever worker claims its job
next, one already running included: it is not reconstructed again, and a whole result is never removed as partial."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from spadscan.worker.holder import Holder
from spadscan.worker.jobs import COMPLETE, Job, mark_complete, scratch_path
from spadscan.worker.pool import Worker
from spadscan.worker import publishing
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from process_helpers import reaped
from test_publishing import _gone_pid
from test_watcher import make_scan
from test_worker_publish_full import LAUNCH, RECON, _scratch, _starts, _until, markers  # noqa: F401  (markers: a fixture)

HERE = Path(__file__).resolve().parent


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_running_worker_publishes_the_result_a_stopped_worker_left_instead_of_running_the_job_again(
        tmp_path, arun, markers):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "a")
    log = tmp_path / "first.log"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")])}
    lines: list[str] = []
    second = Worker(WorkerConfig(root=root, poll_s=0.05, recon=RECON), log=lines.append)

    async def main(first):
        while "could not publish the finished result of a-fast" not in log.read_text():  # the disk is full for it
            assert first.poll() is None, log.read_text()
            await asyncio.sleep(0.05)
        stop = asyncio.Event()
        run = asyncio.create_task(second.run(stop))  # already running when the first one stops
        await _until(lambda: lines or run.done())
        first.send_signal(signal.SIGTERM)
        assert await asyncio.to_thread(first.wait, 60) == 0, log.read_text()
        await _until(lambda: second.settled.get("a-fast") or run.done())
        stop.set()
        await run

    with open(log, "w") as out, reaped(subprocess.Popen([sys.executable, "-c", LAUNCH, str(root)], env=env,
                                                         stdout=out, stderr=subprocess.STDOUT)) as (first,):
        arun(main(first))
    result = root / "a" / "recon" / "a-fast"
    assert second.settled == {"a-fast": "done"}, lines
    assert len(_starts(markers, "a")) == 1, "published as it was, not reconstructed again"
    assert (result / "mesh.ply").is_file() and (result / COMPLETE).is_file() and _scratch(root, "a") == []
    assert any(line.startswith("a-fast: published the finished result an earlier attempt left in .tmp-a-fast-")
               and line.endswith(f"-> {result}") for line in lines), lines
    assert second.queue.job_paths()["a-fast"][0] == "done"
    assert second.queue.attempts("a-fast") == 0, "neither a stopped claim nor the publishing one is an attempt"
    later: list[str] = []
    asyncio.run(Worker(WorkerConfig(root=root, poll_s=0.05, once=True, recon=RECON), log=later.append).run())
    assert not any("partial" in line for line in later), later


def _left_behind(root: Path) -> tuple[Queue, Path]:
    """A job whose claim by a worker now gone finished, marked its result complete and gave the job back."""
    queue = Queue.for_root(root)
    queue.enqueue(Job(id="s-fast", scan="s"))
    gone = queue.claim(Holder(**{**Holder.current().to_dict(), "pid": _gone_pid(), "pid_start": ""}))
    scratch = scratch_path(gone.job, root, gone.token)
    scratch.mkdir(parents=True)
    (scratch / "mesh.ply").write_text("the finished mesh")
    (scratch / "report.json").write_text("{}")
    mark_complete(scratch, gone.job.id, gone.token, queue.path)
    assert queue.release(gone, "worker stopped before it could publish the result")
    return queue, scratch


def test_a_whole_left_result_is_not_removed_while_its_job_is_held_and_its_holder_publishes_it(tmp_path):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    queue, scratch = _left_behind(root)
    held = queue.claim()  # a live worker claimed the job; another worker reconciles meanwhile
    lines: list[str] = []
    publishing.reconcile(queue, root, lines.append, startup=True)
    assert scratch.is_dir() and lines == [], lines
    assert publishing.left_result(queue, held, root) == scratch
    final, aside = publishing.publish_left(queue, held, scratch, root)
    assert (final / "mesh.ply").read_text() == "the finished mesh" and aside is None and not scratch.exists()
    assert queue.job_paths()["s-fast"][0] == "done"
    assert queue.record("s-fast", held.token)["adopted"] and queue.attempts("s-fast") == 0, "nothing ran again"
