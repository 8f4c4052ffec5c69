"""A long-running worker meets a full disk or a failing pass: it says so once, keeps going, and a worker that must end
still stops its jobs first."""

from __future__ import annotations

import asyncio
import errno
import time
from pathlib import Path

import pytest

from spadscan.worker.pool import Worker
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan
from test_worker_process import pid_alive

RECON = "test_worker_process:marker_recon"


@pytest.fixture
def markers(tmp_path, monkeypatch):
    d = tmp_path / "markers"
    d.mkdir()
    monkeypatch.setenv("MARKERS", str(d))
    monkeypatch.setenv("SLEEP_S", "0")
    return d


async def _until(predicate, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("timed out waiting")
        await asyncio.sleep(0.02)


@pytest.mark.usefixtures("recon_stand_ins", "markers")
def test_a_full_disk_while_queuing_is_said_once_and_later_scans_are_still_queued(tmp_path, arun):
    root = tmp_path / "captures"
    root.mkdir()
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, poll_s=0.05, recon=RECON), log=lines.append)
    enqueue, failures = worker.queue.enqueue, []

    def full_disk_for_b(job):
        if job.scan == "b" and len(failures) < 3:  # three passes in a row meet a full disk
            failures.append(job.scan)
            raise OSError(errno.ENOSPC, "No space left on device", str(worker.queue.path / "tmp"))
        return enqueue(job)

    worker.queue.enqueue = full_disk_for_b

    async def main():
        stop = asyncio.Event()
        run = asyncio.create_task(worker.run(stop))
        make_scan(root, "b")
        await _until(lambda: len(failures) == 3)
        make_scan(root, "c")  # the disk has room again
        await _until(lambda: worker.settled.get("b-fast") == "done" and worker.settled.get("c-fast") == "done")
        stop.set()
        await run

    arun(main())
    trouble = [line for line in lines if "look for scans" in line]
    assert trouble == [f"could not look for scans: [Errno 28] No space left on device: "
                       f"'{worker.queue.path / 'tmp'}'; trying again every 0.05 s",
                       "could look for scans again"], lines


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_worker_that_ends_on_an_error_stops_its_jobs_first(tmp_path, arun, markers, monkeypatch):
    """An error the watcher cannot survive ends the worker loudly, and its running job is stopped and given back,
    not left running with nobody to heartbeat its lease."""
    import spadscan.worker.watcher as watcher

    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "a")
    release = tmp_path / "release"
    monkeypatch.setenv("RELEASE", str(release))  # the job runs until the test lets it end
    passes = []

    def scan_once_then_fail(*args):
        passes.append(1)
        if len(passes) > 1 and markers_started(markers):
            # The job processes running as the bug strikes (read here: the worker stops them before the test's
            # own wait for the marker may wake up)
            pids.extend(c.proc.pid for c in worker.children.values())
            raise RuntimeError("a bug in the watcher")
        return real_scan_once(*args)

    real_scan_once = watcher.scan_once
    monkeypatch.setattr(watcher, "scan_once", scan_once_then_fail)
    worker = Worker(WorkerConfig(root=root, poll_s=0.05, recon=RECON, stop_grace_s=5), log=lambda line: None)
    pids = []

    async def main():
        run = asyncio.create_task(worker.run(asyncio.Event()))
        with pytest.raises(RuntimeError, match="a bug in the watcher"):
            await run

    arun(main())
    assert pids and not any(pid_alive(pid) for pid in pids), "its job process was stopped"
    assert worker.queue.counts()["running"] == 0 and worker.queue.counts()["queued"] == 1, "and the job given back"


def markers_started(markers: Path) -> bool:
    return any(markers.glob("a.*.start"))

