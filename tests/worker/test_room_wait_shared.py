"""A job given back on a full disk is claimed by no worker until its room is made or its retry time has come: its
attempt record carries the wait (disk_room.RoomWait.note), and `Queue.claim` takes no job meanwhile, since any other
job writes its log and result where that one did. Another worker on the same root, which never met the full disk,
waits too and says so, instead of running the job into the full disk again and using up its full-disk tries."""

from __future__ import annotations

import asyncio
import errno
import os
import time
import types

import pytest

import spadscan.worker.disk_room as disk_room
from spadscan.worker.disk_room import RoomWait, mount_point
from spadscan.worker.jobs import Job
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from test_worker_disk_full import JOB, PAGE, RECON, refused_until_room, until


def fake_clock(monkeypatch) -> dict:
    """disk_room's wall clock (time.time), set by the test: {"now": seconds}; its monotonic one, {"monotonic"}, runs
    on from the real one's reading, moved by the test."""
    clock = {"now": 1_700_000_000.0, "monotonic": time.monotonic()}
    monkeypatch.setattr(disk_room, "time", types.SimpleNamespace(time=lambda: clock["now"],
                                                                 monotonic=lambda: clock["monotonic"],
                                                                 strftime=time.strftime, gmtime=time.gmtime))
    return clock


def given_back_on_a_full_disk(q: Queue, tmp_path, job_id: str = "a-fast") -> RoomWait:
    """Claim `job_id` and give it back as a worker does whose job met a full disk in `tmp_path`: the wait in its
    record."""
    claim = q.claim()
    assert claim.job.id == job_id
    wait = RoomWait.begin(tmp_path, held=0, retry_s=600.0, job=job_id, roots=q.roots)
    assert q.release(claim, "no room left on the disk", outcome="disk_full", room=wait.note())
    return wait


def test_no_job_is_claimed_while_one_given_back_on_a_full_disk_waits_for_room(tmp_path, monkeypatch):
    free = {"now": PAGE}
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: free["now"])
    fake_clock(monkeypatch)
    q = Queue(tmp_path / "q", root=tmp_path)
    q.enqueue(Job(id="a-fast", scan="a"))
    wait = given_back_on_a_full_disk(q, tmp_path)
    q.enqueue(Job(id="b-fast", scan="b"))  # another scan's job: its result goes where that one's went
    assert q.room_wait() == ("a-fast", wait.note())
    assert q.claim() is None, "neither the job that met the full disk nor any other is claimed"
    assert q.records("a-fast")[-1]["room"] == wait.note(), "the record says what the job waits for"
    free["now"] = wait.need - 1
    assert q.claim() is None
    free["now"] = wait.need
    assert q.room_wait() is None
    assert q.claim().job.id == "a-fast", "room made: claimed again, first given back first"
    assert q.claim().job.id == "b-fast"


def test_a_job_given_back_on_a_full_disk_is_claimed_again_once_its_retry_time_has_come(tmp_path, monkeypatch):
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: PAGE)  # the disk never frees
    clock = fake_clock(monkeypatch)
    q = Queue(tmp_path / "q", root=tmp_path)
    q.enqueue(Job(id="a-fast", scan="a"))
    wait = given_back_on_a_full_disk(q, tmp_path)
    clock["now"] = wait.retry_unix - 1
    assert q.claim() is None
    clock["now"] = wait.retry_unix
    assert q.claim().job.id == "a-fast", "claimed all the same, in case the room is enough"


def test_a_wait_whose_free_space_cannot_be_asked_holds_claims_until_its_time(tmp_path, monkeypatch):
    clock = fake_clock(monkeypatch)
    q = Queue(tmp_path / "q", root=tmp_path)
    q.enqueue(Job(id="a-fast", scan="a"))
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: PAGE)
    wait = given_back_on_a_full_disk(q, tmp_path)

    def lost(folder):
        raise OSError(errno.ESTALE, "Stale file handle")

    monkeypatch.setattr(disk_room, "free_bytes", lost)
    assert q.claim() is None, "a probe that fails sees no room"
    clock["now"] = wait.retry_unix
    assert q.claim().job.id == "a-fast"


def test_a_damaged_wait_in_a_record_holds_nothing(tmp_path):
    q = Queue(tmp_path / "q", root=tmp_path)
    q.enqueue(Job(id="a-fast", scan="a"))
    claim = q.claim()
    q.release(claim, "no room left on the disk", outcome="disk_full", room={"mount": 3})
    assert q.claim().job.id == "a-fast", "a record edited by hand, or by another version, blocks no queue for good"


def test_an_interrupted_claim_after_the_wait_holds_nothing(tmp_path, monkeypatch):
    """Once the job is claimed again, its wait is over: a later release (a stop) says nothing of room."""
    free = {"now": PAGE}
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: free["now"])
    q = Queue(tmp_path / "q", root=tmp_path)
    q.enqueue(Job(id="a-fast", scan="a"))
    wait = given_back_on_a_full_disk(q, tmp_path)
    free["now"] = wait.need
    q.release(q.claim(), "worker stopped")
    free["now"] = PAGE
    assert q.claim().job.id == "a-fast"


def test_a_claim_whose_record_does_not_fit_puts_the_job_back(tmp_path, monkeypatch):
    """The queue's own disk full: the claim's record cannot be written. The job goes back to queued/ (a rename
    needs no room) instead of sitting in running/, held by nobody, until a lease that no one renews runs out, and
    then counted as an attempt its worker lost."""
    q = Queue(tmp_path / "q", root=tmp_path)
    q.enqueue(Job(id="a-fast", scan="a"))

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(q, "_write_record", full)
    with pytest.raises(OSError):
        q.claim()
    assert q.counts()["queued"] == 1 and q.counts()["running"] == 0
    monkeypatch.undo()
    claim = q.claim()
    assert claim.job.id == "a-fast" and claim.attempt == 1


def test_a_claim_put_back_keeps_the_jobs_place_in_the_queue(tmp_path, monkeypatch):
    """While the queue's disk is full, every poll's claim is put back: the oldest job stays first. Before: its file
    came back with the claim's fresh mtime, behind every other job, and each poll moved the next one to the back."""
    q = Queue(tmp_path / "q")
    for n, job_id in enumerate(("a-fast", "b-fast")):
        q.enqueue(Job(id=job_id, scan=job_id[0]))
        os.utime(q.path / "queued" / f"{job_id}.json", ns=(1_700_000_000 * 10**9 + n, 1_700_000_000 * 10**9 + n))

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(q, "_write_record", full)
    for _ in range(2):  # two polls
        with pytest.raises(OSError):
            q.claim()
    assert (q.path / "queued" / "a-fast.json").stat().st_mtime_ns == 1_700_000_000 * 10**9
    monkeypatch.undo()
    assert [q.claim().job.id, q.claim().job.id] == ["a-fast", "b-fast"], "first queued, first run"


@pytest.mark.usefixtures("recon_stand_ins")
def test_another_worker_waits_for_the_room_a_job_given_back_waits_for(tmp_path, monkeypatch, arun):
    """Worker A's job meets a full disk and goes back to the queue; worker B, started on the same root during A's
    wait, neither claims it (it would meet the full disk again, using one of the job's full-disk tries) nor any
    other job: it says that it waits for room, and where. Once room is made, the job runs once more, and is done."""
    full, probes, root = refused_until_room(tmp_path, monkeypatch)
    a_lines: list[str] = []
    b_lines: list[str] = []
    config = WorkerConfig(root=root, once=True, poll_s=0.05, max_attempts=1, recon=RECON)
    a, b = Worker(config, log=a_lines.append), Worker(config, log=b_lines.append)

    async def scenario():
        tasks = [asyncio.create_task(a.run())]
        try:
            await until(lambda: any("waiting for room" in line for line in a_lines), "A's wait for room")
            tasks.append(asyncio.create_task(b.run()))
            await until(lambda: any("waiting for room" in line or line.startswith(f"{JOB} started")
                                    for line in b_lines), "B's wait for room, or its claim")
            seen = len(probes)
            await until(lambda: len(probes) >= seen + 10, "ten more probes of free space")
            assert not any(line.startswith(f"{JOB} started") for line in b_lines), b_lines
            assert [r["outcome"] for r in a.queue.records(JOB)] == ["disk_full"]
            full.unlink()
            return await asyncio.wait_for(asyncio.gather(*tasks), 90)
        finally:
            for task in tasks:
                if not task.done():
                    task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    settled_a, settled_b = arun(scenario())
    assert {**settled_a, **settled_b} == {JOB: "done"}, (a_lines, b_lines)
    (waiting,) = [line for line in b_lines if "waiting for room" in line]
    assert waiting.startswith(f"waiting for room on {mount_point(root)} before claiming another job: {JOB} went "
                              f"back to the queue on a full disk there (4.1 kB free when it did, waiting for 1.1 MB"), \
        waiting
    assert [r["outcome"] for r in a.queue.records(JOB)] == ["disk_full", "done"], "one full-disk try used, not more"
