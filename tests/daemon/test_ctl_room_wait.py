"""A worker that met a full disk waits for room before it claims another job, and says so in its presence file
(`room_wait`: {"mount", "folder", "free_bytes", "need_bytes", "since_unix", "retry_unix", "quota"}, null when it does
not wait). While every worker present waits so, `ctl status` and `ctl wait` say that the scan's queued live job waits
for room, where, and by when a worker claims again, instead of "a worker takes it at its next look"; so do they while
a job given back to the queue on a full disk holds every claim (Queue.room_waits), whether or not a worker says it
waits, and with no worker present they say to start one as well; `status --json` lists each waiting worker's
`room_wait`. A worker that does not write the key (an older one) waits for nothing. The presence files are written
here by hand, as a worker writes them."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

import spadscan.worker.disk_room as disk_room
from spadscan.commands.ctl import live_line, live_status
from spadscan.worker.disk_room import ROOM_RETRY_MAX_S, RoomWait
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue

from test_ctl_live_queue import ELSEWHERE, captures, ctl_status, status_of, worker_present

MB = 1_000_000


def room_wait(mount: str = "/mnt/scratch", free: int | None = 12 * MB, need: int | None = 40 * MB,
              retry_in_s: float = 600.0, quota: bool = False) -> dict:
    now = time.time()
    return {"mount": mount, "folder": f"{mount}/caps/q1/recon", "free_bytes": free, "need_bytes": need,
            "since_unix": now - 5.0, "retry_unix": now + retry_in_s, "quota": quota}


def set_room_wait(root: Path, holder: Holder, value) -> None:
    """Give the presence file of `holder` a `room_wait` (or take the key out: `...`), as the worker writes it."""
    [path] = (Queue.for_root(root).path / "workers").glob(f"{holder.host}-{holder.pid}-*.json")
    data = json.loads(path.read_text())
    if value is ...:
        data.pop("room_wait", None)
    else:
        data["room_wait"] = value
    path.write_text(json.dumps(data, indent=1) + "\n")


def utc(unix: float) -> str:
    """A time as `worker --status` says it: '2025-03-01 14:05 UTC'."""
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(unix))


@pytest.fixture
def idle(tmp_path) -> Path:
    """One worker with a job process free, and mug's live job queued."""
    return captures(tmp_path, {}, [(Holder.current(), 1, ())])


def test_a_worker_waiting_for_room_is_said_instead_of_its_next_look(idle, monkeypatch, capsys):
    """Before: 'a worker takes it at its next look', while the worker claimed nothing until room was made."""
    me = Holder.current()
    waiting = room_wait()
    set_room_wait(idle, me, waiting)
    said = (f"the worker waits for room on /mnt/scratch (12 MB free, 40 MB needed): make room there; it claims again "
            f"by {utc(waiting['retry_unix'])} (sooner once there is room)")
    queued = live_status(status_of(idle))["queued"]
    assert queued["said"] == said, queued["said"]
    assert live_line({"queued": queued}) == f"live reconstruction queued: {said}"
    shown, out = ctl_status(idle, monkeypatch, capsys, "--json")
    assert out.count("\n") == 1 and shown["live"]["queued"]["said"] == said
    assert shown["live"]["queued"]["room_waits"] == {f"{me.host} pid {me.pid}": waiting}


def test_every_worker_waiting_names_each_disk_and_the_first_claim(tmp_path):
    me = Holder.current()
    root = captures(tmp_path, {}, [(me, 1, ()), (ELSEWHERE, 2, ())])
    later, sooner = room_wait(retry_in_s=1800.0), room_wait("/data", free=None, need=None, retry_in_s=300.0,
                                                            quota=True)
    set_room_wait(root, me, later)
    set_room_wait(root, ELSEWHERE, sooner)
    queued = live_status(status_of(root))["queued"]
    assert queued["said"] == (
        f"every worker (2) waits for room on /mnt/scratch (12 MB free, 40 MB needed) and in the disk quota on /data "
        f"(free space unknown): make room there or raise the quota; a worker claims again by "
        f"{utc(sooner['retry_unix'])} (sooner once there is room)"), queued["said"]
    assert set(queued["room_waits"]) == {f"{me.host} pid {me.pid}", f"{ELSEWHERE.host} pid {ELSEWHERE.pid}"}


def test_a_worker_that_can_claim_is_still_said_as_before(tmp_path):
    """One worker waits for room: another with a process free takes the job; one whose processes are busy makes it
    wait for its jobs (the waiting worker's process does not count)."""
    me = Holder.current()
    root = captures(tmp_path, {}, [(me, 1, ()), (ELSEWHERE, 1, ())])
    set_room_wait(root, me, room_wait())
    queued = live_status(status_of(root))["queued"]
    assert queued["said"] == "a worker takes it at its next look"
    assert list(queued["room_waits"]) == [f"{me.host} pid {me.pid}"]
    busy = captures(tmp_path / "busy", {"q1-fast": ELSEWHERE}, [(me, 1, ()), (ELSEWHERE, 1, ("q1-fast",))])
    set_room_wait(busy, me, room_wait())
    assert live_status(status_of(busy))["queued"]["said"] == (
        "waiting for q1-fast to finish (the worker runs 1 job at a time; `--processes 2` runs 2)")


@pytest.mark.parametrize("value", [..., None, "full", {"free_bytes": 3}, {"mount": ""}])
def test_no_room_wait_or_one_of_another_shape_waits_for_nothing(idle, value):
    """An older worker writes no key; one not waiting writes null; a value of another shape says nothing."""
    set_room_wait(idle, Holder.current(), value)
    queued = live_status(status_of(idle))["queued"]
    assert queued["said"] == "a worker takes it at its next look" and queued["room_waits"] == {}


@pytest.mark.parametrize("odd", [{"free_bytes": "lots"}, {"retry_unix": float("nan")}, {"quota": 1}])
def test_a_damaged_room_wait_is_read_as_the_worker_reads_it_no_wait(idle, odd):
    """ctl reads the presence files through the worker's own reader (presence.present_workers): a note it cannot
    read is no wait, not a wait with figures made up."""
    set_room_wait(idle, Holder.current(), {**room_wait(), **odd})
    queued = live_status(status_of(idle))["queued"]
    assert queued["said"] == "a worker takes it at its next look" and queued["room_waits"] == {}


def test_unknown_free_space_is_said_as_unknown_and_a_retry_past_the_longest_wait_is_bounded(idle):
    """No worker waits longer than ROOM_RETRY_MAX_S (an hour): a retry noted past that (a damaged file) is said as
    its start plus that. Before: no time was said."""
    waiting = {**room_wait(), "free_bytes": None, "need_bytes": None, "retry_unix": 1e300}
    set_room_wait(idle, Holder.current(), waiting)
    assert live_status(status_of(idle))["queued"]["said"] == (
        f"the worker waits for room on /mnt/scratch (free space unknown): make room there; it claims again by "
        f"{utc(waiting['since_unix'] + ROOM_RETRY_MAX_S)} (sooner once there is room)")


def test_the_claim_is_said_by_the_last_wait_that_holds_the_queue(tmp_path, monkeypatch):
    """A job given back to the queue on a full disk holds every claim until its room is made or its retry time
    comes: the worker's own wait ends in 10 min, but it claims nothing before the queued job's wait ends in 50.
    Before: the first of the workers' own retries was said."""
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: 12 * MB)  # the disk stays full
    root = tmp_path / "caps"
    (root / "mug").mkdir(parents=True)
    queue = Queue.for_root(root)
    queue.enqueue(Job(id="q2-fast", scan="q2"))
    given = queue.claim()
    held = RoomWait.begin(root / "q2" / "recon", held=0, retry_s=3000.0, job="q2-fast", roots=queue.roots)
    assert queue.release(given, "no room left on the disk", outcome="disk_full", room=held.note())
    queue.enqueue(Job(id="mug-fast", scan="mug", live=True))
    me = Holder.current()
    worker_present(root, me, 1)
    set_room_wait(root, me, room_wait(retry_in_s=600.0))
    said = live_status(status_of(root))["queued"]["said"]
    assert said.endswith(f"; it claims again by {utc(held.retry_unix)} (sooner once there is room)"), said
    # every disk that holds the claims is named, the queued job's as well as the worker's own. Before: /mnt/scratch
    # alone
    assert said.startswith(f"the worker waits for room on /mnt/scratch (12 MB free, 40 MB needed) and {held.where} "
                           f"(12 MB free, "), said


def test_a_wait_noted_ahead_of_this_clock_is_still_said(idle):
    """A worker whose clock runs more than ROOM_SKEW_S ahead waits all the same: ctl and `worker --status` say where.
    The skew matters only to the queue's gate. Before: ctl said no wait, or 'waits for room : make room there'."""
    from spadscan.worker.presence import waiting_for_room

    ahead = {**room_wait(), "since_unix": time.time() + 3600.0, "retry_unix": time.time() + 4200.0}
    set_room_wait(idle, Holder.current(), ahead)
    said = live_status(status_of(idle))["queued"]["said"]
    assert said.startswith("the worker waits for room on /mnt/scratch (12 MB free, 40 MB needed): make room there")
    assert "on /mnt/scratch" in waiting_for_room(ahead)


def given_back(root: Path, job_id: str = "mug-fast", retry_s: float = 600.0) -> RoomWait:
    """Job `job_id` (of the scan its id's first part names; mug's is live) claimed and given back to the queue on a
    full disk as a worker gives it back: its attempt record's `room` the wait it began, on the filesystem that holds
    `root`. The queue's own gate then lets no claim succeed."""
    scan = job_id.rsplit("-", 1)[0]
    queue = Queue.for_root(root)
    queue.enqueue(Job(id=job_id, scan=scan, live=scan == "mug"))
    claim = queue.claim()
    wait = RoomWait.begin(root / scan / "recon", held=0, retry_s=retry_s, job=job_id, roots=queue.roots)
    assert queue.release(claim, "no room left on the disk", outcome="disk_full", room=wait.note())
    assert queue.claim() is None
    return wait


def held_line(wait: RoomWait, tail: str) -> str:
    """What ctl (and the dashboard) say of a queue that mug-fast's wait holds, the disk at 12 MB free."""
    promise = "no claim succeeds before" if "no worker is running" in tail else "a worker claims again by"
    return (f"no job is claimed while mug-fast waits for room {wait.where} (12 MB free, "
            f"{disk_room.size_text(wait.need)} needed): make room there{tail}; {promise} "
            f"{utc(wait.retry_unix)} (sooner once there is room)")


def test_a_queued_jobs_wait_that_holds_the_queue_is_said_though_the_worker_does_not_wait(tmp_path, monkeypatch,
                                                                                        capsys):
    """A worker present that does not (yet) say it waits (between two looks, just started, its presence file not
    fitting on the full disk) claims nothing while the live job's own wait holds the queue. Before: 'a worker takes
    it at its next look', while the dashboard said the wait."""
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: 12 * MB)  # the disk stays full
    root = tmp_path / "caps"
    (root / "mug").mkdir(parents=True)
    wait = given_back(root)
    worker_present(root, Holder.current(), 1)
    said = held_line(wait, "")
    shown, out = ctl_status(root, monkeypatch, capsys, "--json")
    assert shown["live"]["queued"]["said"] == said, shown["live"]["queued"]["said"]
    assert shown["live"]["queued"]["room_waits"] == {}
    assert live_line(shown["live"]) == f"live reconstruction queued: {said}"


def test_a_held_queue_with_no_worker_says_to_start_one_and_the_wait(tmp_path, monkeypatch):
    """Before: 'no worker is running: start one with ...' alone, though a worker started then claims nothing until
    the room is made."""
    from spadscan.worker.presence import start_command

    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: 12 * MB)
    root = tmp_path / "caps"
    (root / "mug").mkdir(parents=True)
    wait = given_back(root)
    start = f"{start_command(root, Queue.for_root(root).path)} --live"
    assert live_status(status_of(root))["queued"]["said"] == held_line(
        wait, f"; no worker is running: start one with `{start}`")
