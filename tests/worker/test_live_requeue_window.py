"""A live job given back to the queue hands its live status over to its next attempt without a gap: a reader of
`<scan>/recon/live/` sees the given-back attempt's 'queued' note, then the new attempt's own first status, never the
earlier attempt's word over a job that runs again, nor a new status beside the earlier attempt's mesh or preview.

Two hand-overs are checked, each at the exact point between its writes (hooks, not timing):

- the new attempt clears the earlier one's mesh and preview and writes its first status with nothing in between: its
  set-up (torch, the device, the ground truth: half a second or more) comes after that status;
- the worker that gives the job back writes the 'queued' note while it still holds the job: once the job is back in
  queued/, another worker's attempt may begin at once, and a note written after would stand over its status."""

from __future__ import annotations

import asyncio
import dataclasses
import errno
import json
import os
from pathlib import Path
from types import SimpleNamespace

import pytest

import spadscan.worker.jobs as jobs
import spadscan.worker.live.job as live_job
import spadscan.worker.pool as pool
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.live_status import LiveStatus, read_status, status_path, write_status
from spadscan.worker.jobs import Job
from spadscan.worker.live.follower import ScanProgress
from spadscan.worker.live.publish import MESH, PREVIEW
from spadscan.worker.pool import Unpublished, Worker
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

JOB = "s-fast"
EARLIER = LiveStatus(views_used=38, views_published=60, steps=563, state="live", chamfer_mm=68.6505,
                     updated_utc="2026-12-03T13:17:00.000+00:00", views_planned=60, job=JOB)
"""The last status of an attempt that was following the scan: 38 views fitted, 563 steps, 68.65 mm."""
QUEUED = dataclasses.replace(EARLIER, state="queued", note="its worker was stopped; the job is back in the queue")
RUNNING = ScanProgress(state="running", reason=None, views_published=9, views_planned=60, new_chunks=9)
"""What the new attempt's first poll finds: a scan still recorded, 9 views published."""


class SetUpReached(Exception):
    """Raised where the new attempt's set-up begins: the test has seen what it wanted."""


def seen(folder: Path) -> tuple:
    """What a reader of the live folder sees now: (state, views used, steps, Chamfer, note, mesh?, preview?)."""
    try:
        status = read_status(folder / "status.json")
    except CaptureError:
        return (None,) * 5 + ((folder / MESH).exists(), (folder / PREVIEW).exists())
    return (status.state, status.views_used, status.steps, status.chamfer_mm, status.note,
            (folder / MESH).exists(), (folder / PREVIEW).exists())


def seen_status(status: LiveStatus) -> tuple:
    """What `seen` shows of `status` (the files aside)."""
    return (status.state, status.views_used, status.steps, status.chamfer_mm, status.note)


def earlier_attempt(root: Path, status: LiveStatus) -> Path:
    """The live folder of scan `s` as an earlier attempt left it: `status`, its mesh and its preview."""
    folder = root / "s" / "recon" / "live"
    folder.mkdir(parents=True)
    write_status(folder, status)
    (folder / MESH).write_text("the earlier attempt's mesh")
    (folder / PREVIEW).write_bytes(b"\x89PNG the earlier attempt's preview")
    return folder


def watch_every_change(monkeypatch, folder: Path) -> list[tuple]:
    """What a reader sees after every rename into `folder` and every removal there (temporary files aside)."""
    views: list[tuple] = []
    replace, unlink = os.replace, Path.unlink

    def replaced(src, dst, *args, **kwargs):
        replace(src, dst, *args, **kwargs)
        if Path(dst).parent == folder:
            views.append(seen(folder))

    def unlinked(path, *args, **kwargs):
        unlink(path, *args, **kwargs)
        if path.parent == folder and not path.name.startswith("."):
            views.append(seen(folder))

    monkeypatch.setattr(os, "replace", replaced)
    monkeypatch.setattr(Path, "unlink", unlinked)
    return views


@pytest.mark.parametrize("earlier", [QUEUED, EARLIER], ids=["queued note", "dead worker's attempt"])
def test_a_new_attempt_says_its_first_status_as_it_clears_the_earlier_attempt_before_its_set_up(
        tmp_path, monkeypatch, earlier):
    root = tmp_path / "captures"
    folder = earlier_attempt(root, earlier)
    during_set_up: list[tuple] = []

    def set_up(run, progress, gt):
        during_set_up.append(seen(folder))
        raise SetUpReached

    def ground_truth(manifest, out):  # the set-up's first step (a built-in scene's mesh: about a second)
        during_set_up.append(seen(folder))
        return None, None

    monkeypatch.setattr(live_job, "ScanFollower", lambda scan: SimpleNamespace(poll=lambda: RUNNING))
    monkeypatch.setattr(jobs, "ground_truth", ground_truth)
    monkeypatch.setattr(live_job.LiveRun, "start", set_up)
    views = watch_every_change(monkeypatch, folder)
    with pytest.raises(SetUpReached):
        live_job.execute_live_job(Job(id=JOB, scan="s", live=True, device="cpu"), root, tmp_path / "out",
                                  log=lambda line: None)
    first = ("waiting", 0, 0, None, "making the first fit of 9 views (loading them, carving their hull)", False, False)
    # The set-up takes half a second on a CPU, more where a GPU starts: all that while the job runs, and its status
    # must be its own, not the earlier attempt's 'queued' note (nor the figures of an attempt whose worker died)
    # beside a mesh and preview no longer there.
    assert during_set_up == [first, first], during_set_up
    # Never the new attempt's status beside the earlier attempt's mesh or preview: cleared first, then said.
    new = [i for i, view in enumerate(views) if view[0] == "waiting"]
    assert new and all(view[-2:] == (False, False) for view in views[new[0]:]), views
    assert all(view[:5] == seen_status(earlier) for view in views[:new[0]]), views


@pytest.fixture
def held(tmp_path):
    """A worker (in this process) holding the live job of scan `s`, whose process has ended; the earlier attempt's
    live status says it was following the scan."""
    root = tmp_path / "captures"
    earlier_attempt(root, EARLIER)
    worker = Worker(WorkerConfig(root=root, max_attempts=3), log=lambda line: None)
    worker.queue.enqueue(Job(id=JOB, scan="s", live=True, device="cpu"))
    claim = worker.queue.claim()
    outcome = tmp_path / "outcome.json"
    outcome.write_text("{}")  # a process that died without a word: a crash, retried
    child = SimpleNamespace(claim=claim, proc=SimpleNamespace(returncode=-9, pid=None), scratch=tmp_path / "scratch",
                            outcome=outcome, log=tmp_path / "job.log", stopped_why=None)
    return SimpleNamespace(root=root, worker=worker, child=child)


def next_attempt_begins_after(monkeypatch, held, method: str) -> list[tuple]:
    """Make `held.worker.queue.<method>` (the call that puts the job back in queued/) be followed at once by another
    worker claiming the job and its attempt beginning: a complete scan's rerun, whose 'final' is its only status until
    its result is published. Returns what a reader saw as the job went back to the queue."""
    folder = held.root / "s" / "recon" / "live"
    given_back = getattr(held.worker.queue, method)
    at_give_back: list[tuple] = []

    def then_taken(claim, *args, **kwargs):
        state = given_back(claim, *args, **kwargs)
        at_give_back.append(seen(folder))
        other = Queue.for_root(held.root).claim()
        assert other is not None and other.job.id == JOB, "the job was back in the queue"
        done = dataclasses.replace(RUNNING, state="complete", views_published=60, views_planned=60)
        live_job.status_finishing(held.root / "s", other.job, done, "reconstructing it from scratch")
        return state

    monkeypatch.setattr(held.worker.queue, method, then_taken)
    return at_give_back


async def stop_worker(held) -> None:
    """The held job's worker stops (`Worker._stop_children`): its job's process has already ended."""
    ended = asyncio.get_running_loop().create_future()
    ended.set_result(0)
    held.worker.children[JOB] = SimpleNamespace(**vars(held.child), wait=ended)
    await held.worker._stop_children()


def rerun_status(root: Path) -> tuple:
    status = read_status(status_path(root / "s"))
    return status.state, status.views_used, status.steps, status.note


def test_a_stopping_worker_says_queued_before_it_gives_the_job_back_never_over_the_next_attempt(
        held, monkeypatch, arun):
    at_release = next_attempt_begins_after(monkeypatch, held, "release")

    arun(stop_worker(held))
    assert rerun_status(held.root) == ("final", 0, 0, "reconstructing it from scratch")
    assert [view[0] for view in at_release] == ["queued"], at_release  # said while the job was still held


def test_a_crashed_live_job_says_queued_before_it_is_retried_never_over_the_next_attempt(held, monkeypatch):
    at_crash = next_attempt_begins_after(monkeypatch, held, "crash")
    held.worker._settle(held.child)
    assert rerun_status(held.root) == ("final", 0, 0, "reconstructing it from scratch")
    assert [view[0] for view in at_crash] == ["queued"], at_crash  # said while the job was still held
    assert "process crashed" in at_crash[0][4]


def test_a_crash_on_the_last_attempt_never_says_queued_only_stopped(held, monkeypatch):
    held.worker.queue.max_attempts = 1
    seen_on_the_way = watch_every_change(monkeypatch, held.root / "s" / "recon" / "live")
    held.worker._settle(held.child)
    assert [view[0] for view in seen_on_the_way] == ["stopped"], seen_on_the_way


def test_a_worker_whose_lease_was_taken_over_leaves_the_new_holders_status_alone(held, arun):
    queue = Queue.for_root(held.root)
    assert queue.reclaim_expired(now=held.child.claim.started + 3600) == [(JOB, "queued")]
    other = queue.claim()
    done = dataclasses.replace(RUNNING, state="complete", views_published=60, views_planned=60)
    live_job.status_finishing(held.root / "s", other.job, done, "reconstructing it from scratch")

    arun(stop_worker(held))
    assert rerun_status(held.root) == ("final", 0, 0, "reconstructing it from scratch")


def test_a_live_job_that_failed_on_its_input_never_says_queued_only_stopped(held, monkeypatch):
    held.child.outcome.write_text(json.dumps({"ok": False, "kind": "input", "error": "no returns above the noise"}))
    held.child.proc.returncode = 1  # attempts are left (1 of 3): an input failure is still not retried
    seen_on_the_way = watch_every_change(monkeypatch, held.root / "s" / "recon" / "live")
    lines: list[str] = []
    held.worker.log = lines.append
    held.worker._settle(held.child)
    assert [view[0] for view in seen_on_the_way] == ["stopped"], seen_on_the_way
    # The failed line says how to run the job again once its input is mended (a torn chunk moved out, say).
    assert lines[-1].startswith(f"{JOB} failed after ") and "no returns above the noise" in lines[-1], lines
    assert lines[-1].endswith(f"(once the cause is fixed, `spadscan worker --root {held.root} --retry-failed` "
                              f"queues it again)"), lines


def test_a_queue_unreachable_as_a_live_job_crashes_leaves_the_worker_running(held, monkeypatch):
    def broken(call):
        def fails_on_running(path, *args, **kwargs):
            if "/running/" in str(path):
                raise OSError(errno.EIO, "Input/output error", str(path))
            return call(path, *args, **kwargs)
        return fails_on_running

    monkeypatch.setattr(os, "utime", broken(os.utime))
    monkeypatch.setattr(os, "rename", broken(os.rename))
    lines: list[str] = []
    held.worker.log = lines.append
    held.worker._settle(held.child)  # the worker's other jobs go on: nothing escapes
    assert any("could not record it" in line for line in lines), lines


def disk_full(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_a_stopping_worker_whose_result_could_not_be_published_says_queued_before_it_gives_the_job_back(
        held, monkeypatch):
    # The job's process finished, but its result never fitted on the disk; the worker now stops and gives it back.
    held.child.scratch.mkdir()
    held.worker.unpublished[JOB] = Unpublished(held.child, 12.0, {})
    monkeypatch.setattr(pool, "publish_claim", disk_full)
    at_release = next_attempt_begins_after(monkeypatch, held, "release")

    held.worker._leave_unpublished()
    assert rerun_status(held.root) == ("final", 0, 0, "reconstructing it from scratch")
    assert [view[0] for view in at_release] == ["queued"], at_release  # said while the job was still held
    assert "could publish the result" in at_release[0][4], at_release


def test_a_left_result_that_could_not_be_published_says_queued_before_the_job_goes_back(held, monkeypatch, tmp_path):
    # A claim finds the finished result an earlier attempt left, and cannot publish it either (the disk still full).
    monkeypatch.setattr(pool, "publish_left", disk_full)
    at_release = next_attempt_begins_after(monkeypatch, held, "release")

    held.worker._publish_left(held.child.claim, tmp_path / "left")
    assert rerun_status(held.root) == ("final", 0, 0, "reconstructing it from scratch")
    assert [view[0] for view in at_release] == ["queued"], at_release
    assert "could not publish the result left in" in at_release[0][4], at_release
