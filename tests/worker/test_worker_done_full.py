"""A full disk after a finished result was renamed into place, while the queue records its job as done: the worker
says what really happened (the result is published; only the queue's record is late), never that it was dropped or
will be reconstructed again."""

from __future__ import annotations

import asyncio
import errno

import pytest

from spadscan.worker.jobs import COMPLETE
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan
from test_worker_publish_full import RECON, _starts, _until, markers  # noqa: F401  (markers: a fixture)

pytestmark = pytest.mark.usefixtures("recon_stand_ins")


def test_a_done_record_the_disk_cannot_hold_is_written_later_and_the_job_said_done(tmp_path, arun, markers,
                                                                                    monkeypatch):
    """queue.finish renames the job file to done/, then its attempt record meets the full disk: the lease's heartbeat
    finds no running/ file, which is not a lease lost to another worker."""
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "a")
    full = [True]
    beats = []
    write_record, heartbeat = Queue._write_record, Queue.heartbeat

    def record(self, job_id, token, rec):
        if full[0] and rec.get("outcome") == "done":
            raise OSError(errno.ENOSPC, "No space left on device")
        return write_record(self, job_id, token, rec)

    def beat(self, claim):
        renewed = heartbeat(self, claim)
        beats.append(renewed)
        return renewed

    monkeypatch.setattr(Queue, "_write_record", record)
    monkeypatch.setattr(Queue, "heartbeat", beat)
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, poll_s=0.05, lease_s=0.4, recon=RECON), log=lines.append)

    async def main():
        stop = asyncio.Event()
        run = asyncio.create_task(worker.run(stop))
        dropped = lambda: any("dropped" in line for line in lines)  # noqa: E731
        await _until(lambda: beats.count(False) >= 2 or dropped() or run.done())  # heartbeats found it in done/
        full[0] = False  # room again
        await _until(lambda: "a-fast" in worker.settled or dropped() or run.done())
        stop.set()
        await run

    arun(main())
    result = root / "a" / "recon" / "a-fast"
    assert not any("dropped" in line or "taken over" in line for line in lines), lines
    assert worker.settled == {"a-fast": "done"}, lines
    assert any(line.startswith("a-fast done in ") and line.endswith(f"-> {result}") for line in lines), lines
    rec = worker.queue.records("a-fast")[-1]
    assert (rec["outcome"], rec["result"]) == ("done", str(result))
    assert (result / COMPLETE).is_file() and len(_starts(markers, "a")) == 1


def test_a_worker_stopped_with_its_result_in_place_says_so_and_the_next_one_records_it(tmp_path, arun, markers,
                                                                                       monkeypatch):
    """The result was renamed into place, then moving the job file to done/ meets the full disk (a new directory
    entry); the worker is stopped while the disk is still full."""
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "a")
    tried = []
    settle = Queue._settle

    def full(self, src, job_id, state):
        if state == "done":
            tried.append(job_id)
            raise OSError(errno.ENOSPC, "No space left on device")
        return settle(self, src, job_id, state)

    monkeypatch.setattr(Queue, "_settle", full)
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, poll_s=0.05, recon=RECON), log=lines.append)

    async def main():
        stop = asyncio.Event()
        run = asyncio.create_task(worker.run(stop))
        await _until(lambda: len(tried) >= 2 or run.done())
        stop.set()
        await run

    arun(main())
    monkeypatch.setattr(Queue, "_settle", settle)
    result = root / "a" / "recon" / "a-fast"
    said = [line for line in lines if line.startswith("a-fast stopped")]
    assert said == [f"a-fast stopped before the queue recorded it as done; back in the queue, its result is in place "
                    f"at {result}: the next worker to claim it records the job as done, not reconstructing it "
                    f"again"], lines
    assert not any("reconstructed again" in line for line in lines), lines
    later: list[str] = []
    settled = asyncio.run(Worker(WorkerConfig(root=root, poll_s=0.05, once=True, recon=RECON),
                                 log=later.append).run())
    assert settled == {"a-fast": "done"} and len(_starts(markers, "a")) == 1, later
