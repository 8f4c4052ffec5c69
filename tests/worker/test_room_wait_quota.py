"""A full disk quota (EDQUOT) is one user's, which the filesystem's free space does not show: free space may be
plenty, and grow, while the quota stays full. The wait after a job met one ends on its timer alone, never on a
probe of free space, and the worker says that it is a quota."""

from __future__ import annotations

import asyncio
import errno
import os
import time
import types
from pathlib import Path

import pytest

import spadscan.worker.disk_room as disk_room
from spadscan.worker.disk_room import RoomWait, mount_point
from spadscan.worker.pool import Worker
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan
from test_worker_disk_full import JOB, counted_probes, run_worker, until

MIB = 1 << 20


def quota_recon(capture, out, **kwargs):
    """A stand-in reconstruction that meets a full quota (EDQUOT) while the file $FULL exists, else writes a
    report."""
    if Path(os.environ["FULL"]).exists():
        raise OSError(errno.EDQUOT, "Disk quota exceeded")
    (Path(out) / "report.json").write_text("{}")
    return {}


def fake_clock(monkeypatch) -> dict:
    """disk_room's clock, set by the test: {"now": seconds since the epoch}."""
    clock = {"now": time.time()}
    monkeypatch.setattr(disk_room, "time", types.SimpleNamespace(time=lambda: clock["now"],
                                                                 monotonic=lambda: clock["now"]))
    return clock


def test_a_wait_on_a_full_quota_ends_on_its_timer_alone(tmp_path, monkeypatch):
    free = {"now": 10**12}
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: free["now"])
    clock = fake_clock(monkeypatch)
    wait = RoomWait.begin(tmp_path, held=5 * MIB, retry_s=600.0, quota=True)
    assert wait.need is None and wait.note()["quota"] is True and wait.note()["need_bytes"] is None
    free["now"] += 100 * MIB
    assert wait.over() == (False, free["now"]), "free space says nothing of a quota"
    clock["now"] = wait.retry_unix
    assert wait.over()[0]


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_job_that_meets_a_full_quota_waits_for_its_time_whatever_the_free_space(tmp_path, monkeypatch, arun):
    full = tmp_path / "full"
    full.touch()
    monkeypatch.setenv("FULL", str(full))
    free = {"now": 10**12}
    probes = counted_probes(monkeypatch, lambda folder: free["now"])
    clock = fake_clock(monkeypatch)
    root = tmp_path / "caps"
    make_scan(root, "s")
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05, max_attempts=1,
                                 recon="test_room_wait_quota:quota_recon"), log=lines.append)

    async def scenario():
        async def meanwhile():
            await until(lambda: any("waiting for room" in line for line in lines), "the wait for room")
            free["now"] += 2 * MIB  # room freed on the filesystem, none in the quota
            seen = len(probes)
            await until(lambda: len(probes) >= seen + 10, "ten more probes of free space")
            assert sum(line.startswith(f"{JOB} started") for line in lines) == 1, lines
            assert not any("claiming jobs again" in line for line in lines), lines
            full.unlink()
            clock["now"] = worker.room.retry_unix

        return (await run_worker(worker, meanwhile))[1]

    assert arun(scenario()) == {JOB: "done"}, lines
    mount = mount_point(root)
    (stopped,) = [line for line in lines if line.startswith(f"{JOB} stopped after ")]
    assert (f"no room left in the disk quota: {root / 's' / 'recon'} could not be written (Disk quota exceeded); "
            f"back in the queue") in stopped, stopped
    assert f"make room in this user's disk quota on the filesystem mounted at {mount}, then" in stopped, stopped
    (waiting,) = [line for line in lines if "waiting for room" in line]
    assert waiting == (f"waiting for room in the disk quota on {mount} before claiming another job: a full quota "
                       f"does not show in the free space (1000 GB free), so no probe can tell when room is made: "
                       f"claiming again in 10 min"), waiting
    assert f"waited 10 min for room in the disk quota on {mount}: claiming jobs again, in case room was made" in lines
    full_record, done = worker.queue.records(JOB)
    assert full_record["room"]["quota"] is True and full_record["room"]["need_bytes"] is None
    assert done["outcome"] == "done"
