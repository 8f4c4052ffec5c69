"""A job whose process meets a full disk is not at fault, and a retry would meet the same disk: the worker gives it
back to the queue without counting an attempt, says in one line which folder is full and where to make room, claims
no job until there is room (saying so once), and runs the job once room is made. The job's log says it in one line,
not a traceback, and `worker --status` shows the queued job's reason. A result whose 3D view could not be written
names the command that makes it again."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import importlib.util
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

import spadscan.worker.disk_room as disk_room
import spadscan.worker.pool as pool_module
import spadscan.worker.report.folder_view as folder_view
from spadscan.cli import main as cli_main
from spadscan.worker.disk_room import RoomWait, size_text
from spadscan.worker.jobs import Job, execute_job
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.report.folder_view import ensure_view3d
from spadscan.worker.report.view3d import VIEW3D
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan

RECON = "test_worker_disk_full:filling_recon"
JOB = "s-fast"
WRITE = 256 * 1024
"""Bytes the stand-in reconstruction writes: more than the room a test leaves on its disk."""
PAGE = 4096


def filling_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                  started=None):
    """A stand-in reconstruction that writes WRITE bytes into `out` as $WRITE_WITH says: 'numpy' (ndarray.tofile,
    whose short write on a full disk carries no errno), 'open' (a plain write: ENOSPC), or 'refused' (ENOSPC raised
    while the file $FULL exists: a full disk simulated where no small one can be mounted). Then a report."""
    how, out = os.environ["WRITE_WITH"], Path(out)
    if how == "numpy":
        np.zeros(WRITE, np.uint8).tofile(out / "big.bin")
    elif how == "open":
        with open(out / "big.bin", "wb") as f:
            f.write(b"\0" * WRITE)
    elif Path(os.environ["FULL"]).exists():
        raise OSError(errno.ENOSPC, "No space left on device")
    report = {"preset": preset, "capture": str(capture)}
    (out / "report.json").write_text(json.dumps(report))
    return report


def _e2e_helpers():
    """tests/e2e/e2e_helpers.py, whose `tmpfs` is the suite's one way to mount a small disk (that folder is on the
    import path only when its own tests are collected)."""
    if "e2e_helpers" in sys.modules:
        return sys.modules["e2e_helpers"]
    spec = importlib.util.spec_from_file_location("e2e_helpers", Path(__file__).parents[1] / "e2e" / "e2e_helpers.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def small_disk(path: Path, size: str):
    with _e2e_helpers().tmpfs(path, size) as mounted:
        if not mounted:
            pytest.skip("cannot mount a small tmpfs here (needs root)")
        yield path


def fill_leaving(folder: Path, room: int) -> Path:
    """Fill the filesystem holding `folder` with one file but `room` bytes; returns the file (remove it: room)."""
    filler = folder / "filler"
    st = os.statvfs(folder)
    fd = os.open(filler, os.O_CREAT | os.O_WRONLY)
    try:
        os.posix_fallocate(fd, 0, st.f_bavail * st.f_frsize - room)
    finally:
        os.close(fd)
    return filler


def counted_probes(monkeypatch, free=None) -> list[int]:
    """Count the worker's probes of free space (`disk_room.free_bytes`); `free(folder)` answers them instead of the
    disk where given."""
    calls: list[int] = []
    real = free or disk_room.free_bytes

    def probe(folder):
        calls.append(1)
        return real(folder)

    monkeypatch.setattr(disk_room, "free_bytes", probe)
    return calls


async def until(check, what: str, timeout_s: float = 90.0) -> None:
    """Wait (polling the loop) until check() holds."""
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while not check():
        assert loop.time() < end, f"timed out waiting for {what}"
        await asyncio.sleep(0.02)


async def run_worker(worker: Worker, meanwhile):
    """Run `worker` while `meanwhile()` (a coroutine function: what a test waits for and does, e.g. make room) runs,
    then to its end; returns (what `meanwhile` returned, what the worker settled). The worker is stopped if the
    test fails first."""
    task = asyncio.create_task(worker.run())
    try:
        done = await meanwhile()
        return done, await asyncio.wait_for(task, 90)
    finally:
        if not task.done():
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)


def refused_until_room(tmp_path, monkeypatch) -> tuple[Path, list[int], Path]:
    """A disk full while the file `full` exists: the stand-in job's writes are refused (ENOSPC) and the worker's
    probe of free space reads one page free, else plenty; and a captures root with scan "s". Returns (full, the
    probes' record, the root)."""
    full = tmp_path / "full"
    full.touch()
    monkeypatch.setenv("WRITE_WITH", "refused")
    monkeypatch.setenv("FULL", str(full))
    probes = counted_probes(monkeypatch, lambda folder: PAGE if full.exists() else 10**12)
    root = tmp_path / "caps"
    make_scan(root, "s")
    return full, probes, root


def run_through_full_disk(worker: Worker, lines: list[str], probes: list[int], make_room, arun):
    """Run the worker until it waits for room and has probed for it a few times, check what it says meanwhile,
    make room, and run it to its end; returns (the job's --status row while it waited, what the worker settled)."""
    async def scenario():
        async def meanwhile():
            await until(lambda: any("waiting for room" in line for line in lines), "the wait for room")
            seen = len(probes)
            await until(lambda: len(probes) >= seen + 5, "five more probes of free space")
            row = {r.id: r for r in worker.queue.statuses()}[JOB]
            assert (row.state, row.attempts) == ("queued", 0), row
            assert sum(line.startswith(f"{JOB} started") for line in lines) == 1, "no claim while the disk is full"
            assert sum("waiting for room" in line for line in lines) == 1, "said once"
            make_room()
            return row

        return await run_worker(worker, meanwhile)

    return arun(scenario())


@pytest.mark.usefixtures("recon_stand_ins")
@pytest.mark.parametrize("how", ["numpy", "open"])
def test_a_job_that_meets_a_full_disk_waits_for_room_and_uses_no_attempt(tmp_path, monkeypatch, arun, how):
    """A 2 MB tmpfs, the job queued, then filled but for 64 kB: the stand-in's 256 kB meet the full disk. With one
    attempt allowed, a counted crash would fail the job: it waits instead, and runs once the filler is removed."""
    monkeypatch.setenv("WRITE_WITH", how)
    with small_disk(tmp_path / "disk", "2m") as disk:
        root = disk / "caps"
        make_scan(root, "s")
        Queue.for_root(root).enqueue(Job(id=JOB, scan="s"))
        filler = fill_leaving(disk, 16 * PAGE)
        probes = counted_probes(monkeypatch)
        lines: list[str] = []
        worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05, max_attempts=1, recon=RECON),
                        log=lines.append)
        row, settled = run_through_full_disk(worker, lines, probes, filler.unlink, arun)
        assert settled == {JOB: "done"}, lines
        recon = root / "s" / "recon"
        (stopped,) = [line for line in lines if line.startswith(f"{JOB} stopped after ")]
        assert f"no room left on the disk: {recon} could not be written (" in stopped, stopped
        assert stopped.endswith(f"back in the queue, not counted as an attempt; make room on the filesystem mounted "
                                f"at {disk}, then this worker runs it again by itself"), stopped
        assert row.error.startswith(f"no room left on the disk: {recon} could not be written"), \
            "--status says why the job waits"
        assert f"make room on the filesystem mounted at {disk}" in row.error
        assert any(line.startswith(f"room again on {disk} (") for line in lines), lines
        assert sum(line.startswith(f"{JOB} started (attempt 1 of 1") for line in lines) == 2, lines
        full, done = worker.queue.records(JOB)
        assert (full["outcome"], done["outcome"]) == ("disk_full", "done")
        said = (worker.queue.path / "logs" / f"{JOB}~{full['token']}.log").read_text()
        assert "Traceback" not in said, said  # its one line, when it fits (the queue's logs are on that disk too)
        assert (recon / JOB / "big.bin").stat().st_size == WRITE


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_full_disk_simulated_where_none_can_be_mounted(tmp_path, monkeypatch, arun):
    """The same, anywhere: the stand-in meets ENOSPC while a file says the disk is full, and the worker's probe of
    free space reads that file."""
    full, probes, root = refused_until_room(tmp_path, monkeypatch)
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05, max_attempts=1, recon=RECON), log=lines.append)
    assert run_through_full_disk(worker, lines, probes, full.unlink, arun)[1] == {JOB: "done"}, lines
    full_record = worker.queue.records(JOB)[0]
    said = (worker.queue.path / "logs" / f"{JOB}~{full_record['token']}.log").read_text()
    assert said == f"job stopped: no room left on the disk: {root / 's' / 'recon'}/.tmp-{JOB}-{full_record['token']} " \
                   f"could not be written (No space left on device)\n", "one line, no traceback"
    (waiting,) = [line for line in lines if "waiting for room" in line]
    assert waiting.startswith(f"waiting for room on {disk_room.mount_point(root)} before claiming another job: "
                              f"4.1 kB free, the job needs more (waiting for 1.1 MB"), waiting


def test_a_wait_for_room_ends_with_the_room_it_waits_for_or_after_its_time(tmp_path, monkeypatch):
    free = {"now": 300_000}
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: free["now"])
    wait = RoomWait.begin(tmp_path, held=2_000_000, retry_s=600.0)
    assert (wait.free, wait.need) == (300_000, 2_300_000), "as much again as the partial result took"
    assert wait.over() == (False, 300_000)
    free["now"] = 2_300_000
    assert wait.over() == (True, 2_300_000)
    small = RoomWait.begin(tmp_path, held=10, retry_s=0.0)
    assert small.need == 2_300_000 + disk_room.ROOM_MARGIN and small.over()[0], "its time is up at once"
    assert [disk_room.retry_after(n) for n in (1, 2, 3, 4)] == [600.0, 1200.0, 2400.0, 3600.0]
    assert [size_text(n) for n in (512, 283_000, 1_310_720, 16_400_000)] == ["512 bytes", "283 kB", "1.3 MB", "16 MB"]


def test_a_job_result_without_its_view_names_the_command_that_makes_it_again(tmp_path, monkeypatch):
    """The job's job.json names its redo command; a view that meets a full disk says to make room, then run it."""
    import trimesh

    root = tmp_path / "caps"
    make_scan(root, "s")
    job = Job(id=JOB, scan="s")

    def recon(capture, out, **kwargs):
        trimesh.creation.icosphere(subdivisions=1, radius=0.05).export(Path(out) / "mesh.ply")
        return {}

    out = root / "s" / "recon" / ".tmp-s-fast-test"
    execute_job(job, root, out, recon)
    redo = f"spadscan worker --root {root.resolve()} --redo {JOB}"
    assert json.loads((out / "job.json").read_text())["redo"] == redo

    def full(folder, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(Path(folder) / VIEW3D))

    monkeypatch.setattr(folder_view, "write_view3d", full)
    report: dict = {"warnings": []}
    assert ensure_view3d(report, out) is None
    assert report["warnings"] == [f"no 3D view: {VIEW3D} could not be written (No space left on device); make room "
                                  f"on its disk, then `{redo}` queues the job again, this result moved aside, and a "
                                  f"worker on that root and queue (a running one, or one started with --once) "
                                  f"reconstructs it with its view"]
    (out / "job.json").unlink()
    plain: dict = {}
    ensure_view3d(plain, out)
    assert plain["warnings"] == [f"no 3D view: {VIEW3D} could not be written (No space left on device)"], \
        "a result of no job names no job's command"


def test_help_says_what_the_worker_does_on_a_full_disk(capsys):
    with pytest.raises(SystemExit):
        cli_main(["worker", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "A job whose own process meets a full disk is not at fault" in text, text
    assert "without using an attempt" in text and "the worker claims no job until there is room" in text
    assert "no worker on the queue claims a job while it lasts: another worker waits too" in text
    assert "the worker says it is a quota and waits for the timer alone" in text
    assert "whose small outcome file alone did not fit, is published, not reconstructed again" in text


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_full_disk_that_keeps_out_the_attempt_record_says_so_and_writes_it_later(tmp_path, monkeypatch, arun):
    """The job goes back to the queue (a rename needs no room) while its record does not fit: the line says so, the
    record is written once there is room, and the job then runs on the one attempt it has."""
    full, _, root = refused_until_room(tmp_path, monkeypatch)
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05, max_attempts=1, recon=RECON), log=lines.append)
    write_outcome = worker.queue.write_outcome

    def refused(claim, values):
        if full.exists():
            raise OSError(errno.ENOSPC, "No space left on device")
        write_outcome(claim, values)

    monkeypatch.setattr(worker.queue, "write_outcome", refused)

    async def scenario():
        async def meanwhile():
            await until(lambda: any("waiting for room" in line for line in lines), "the wait for room")
            assert worker.queue.job_paths()[JOB][0] == "queued", "the job went back all the same"
            full.unlink()

        return (await run_worker(worker, meanwhile))[1]

    assert arun(scenario()) == {JOB: "done"}, lines
    (stopped,) = [line for line in lines if line.startswith(f"{JOB} stopped after ")]
    assert ("; back in the queue, but its attempt record could not be written ([Errno 28] No space left on device): "
            "trying again every 0.05 s, then it is not counted as an attempt; make room on the "
            "filesystem") in stopped, stopped
    assert [r["outcome"] for r in worker.queue.records(JOB)] == ["disk_full", "done"]
    assert sum(line.startswith(f"{JOB} started (attempt 1 of 1") for line in lines) == 2, lines


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_job_that_keeps_meeting_a_full_disk_fails_and_says_why(tmp_path, monkeypatch, arun):
    """A job whose result may need more room than the disk ever frees is not run into it for ever (each run fills
    the disk again for every other writer on it): after MAX_FULL_DISK full disks it fails, counted, saying why."""
    full = tmp_path / "full"
    full.touch()
    monkeypatch.setenv("WRITE_WITH", "refused")
    monkeypatch.setenv("FULL", str(full))
    monkeypatch.setattr(pool_module, "MAX_FULL_DISK", 2)
    counted_probes(monkeypatch, lambda folder: PAGE)  # the disk never frees: each wait ends on its timer
    monkeypatch.setattr(pool_module, "retry_after", lambda n: 0.0)
    root = tmp_path / "caps"
    make_scan(root, "s")
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05, max_attempts=3, recon=RECON), log=lines.append)
    assert arun(asyncio.wait_for(worker.run(), 120)) == {JOB: "failed"}, lines
    assert [r["outcome"] for r in worker.queue.records(JOB)] == ["disk_full", "failed"]
    (failed,) = [line for line in lines if line.startswith(f"{JOB} failed after ")]
    assert "no room left on the disk" in failed and "(it met a full disk 2 times: its result may need more room " \
           "than the disk frees)" in failed and "--retry-failed" in failed, failed


def test_a_wait_whose_free_space_cannot_be_read_ends_on_its_timer(tmp_path, monkeypatch):
    """A lost mount (statvfs failing): the wait neither stops claims for good nor is skipped."""
    def lost(folder):
        raise OSError(errno.ESTALE, "Stale file handle")

    monkeypatch.setattr(disk_room, "free_bytes", lost)
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=tmp_path, once=True, poll_s=0.05, recon=RECON), log=lines.append)
    monkeypatch.setattr(pool_module, "retry_after", lambda n: 600.0)
    worker._begin_wait(worker._job_wait(tmp_path, 0, False, None))  # as a job's full disk begins it
    assert worker.room is not None and not worker._room_again(), "the wait goes on: its time is not up"
    worker._begin_wait(worker._job_wait(tmp_path / "other", 0, False, None))
    assert worker.room.retry_s == 600.0 and worker._full_in_row == 1, "a second full disk during it: one wait"
    worker.room.since_unix -= 600.0
    assert worker._room_again() and worker.room is None, "its time is up: claims go on"
    assert any("could not check the free space" in line for line in lines), lines
