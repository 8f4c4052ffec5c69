"""A wait for room noted in the queue (a job's attempt record, disk_room.RoomWait.note) holds every worker's claims,
so it is read with bounds: it never runs longer than a worker ever waits (ROOM_RETRY_MAX_S), one that begins ahead of
the reader's clock (a clock running ahead, a damaged record) holds nothing and is said once, and a need larger than
the whole filesystem is waited for on the timer. Its folder is found under the reader's own queue or captures root
(a second machine mounts them elsewhere), and where it cannot be found there, its free space is unknown: the timer
ends it. A worker's own wait ends on the monotonic clock, whatever the wall clock does. And a worker that waits for
another's job goes on as soon as that job's wait leaves the queue."""

from __future__ import annotations

import time
import types
from pathlib import Path

import pytest

import spadscan.worker.disk_room as disk_room
from spadscan.worker.disk_room import ROOM_RETRY_MAX_S, ROOM_SKEW_S, RoomWait, mount_point, total_bytes
from spadscan.worker.jobs import Job
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from test_worker_disk_full import PAGE, RECON

DAY = 86400.0
YEAR = 365 * DAY


def clocks(monkeypatch) -> dict:
    """disk_room's wall clock ({"now"}) and monotonic one ({"monotonic"}), each set by the test."""
    clock = {"now": 1_700_000_000.0, "monotonic": 5_000.0}
    monkeypatch.setattr(disk_room, "time", types.SimpleNamespace(time=lambda: clock["now"],
                                                                 monotonic=lambda: clock["monotonic"],
                                                                 strftime=time.strftime, gmtime=time.gmtime))
    return clock


def note(folder: Path, since: float, retry_in_s: float = 600.0, **fields) -> dict:
    """A wait for room as a worker notes it, on `folder` (a captures root's scan s), from `since`."""
    return {"mount": "/", "folder": str(folder), "free_bytes": PAGE, "need_bytes": PAGE + (1 << 20),
            "since_unix": since, "retry_unix": since + retry_in_s, "quota": False, "relative_to": "root",
            "relative": "s/recon", **fields}


def given_back(q: Queue, room: dict, *job_ids: str) -> None:
    """Queue `job_ids` and give each back as a worker whose job met a full disk does, its record carrying `room`."""
    for job_id in job_ids:
        q.enqueue(Job(id=job_id, scan=job_id.split("-")[0]))
    claims = [q.claim() for _ in job_ids]
    assert sorted(c.job.id for c in claims) == sorted(job_ids)
    for claim in claims:
        assert q.release(claim, "no room left on the disk", outcome="disk_full", room=room)


@pytest.mark.parametrize("quota", [False, True])
def test_a_wait_noted_to_run_a_year_holds_claims_an_hour_at_most(tmp_path, monkeypatch, quota):
    """Before: claim() returned None for every worker until the year was over."""
    clock = clocks(monkeypatch)
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: PAGE)  # the disk stays full
    q = Queue(tmp_path / "q", root=tmp_path)
    (tmp_path / "s" / "recon").mkdir(parents=True)
    given_back(q, note(tmp_path / "s" / "recon", clock["now"], YEAR, quota=quota,
                       need_bytes=None if quota else PAGE + (1 << 20)), "a-fast")
    doubts: list = []
    assert q.room_wait(None, doubts) is not None and q.claim() is None, "an hour's wait holds"
    assert doubts == [("a-fast", "its wait for room runs 525600 min, longer than any worker waits: waited for 60 "
                                 "min from its start at most")], doubts
    clock["now"] += ROOM_RETRY_MAX_S
    assert q.claim().job.id == "a-fast", "the longest wait a worker makes is over"


def test_a_wait_that_begins_ahead_of_this_clock_holds_nothing_and_is_said_once(tmp_path, monkeypatch):
    """Before: a record from a machine whose clock ran a day ahead held every claim for that day and more."""
    clock = clocks(monkeypatch)
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: PAGE)
    worker = Worker(WorkerConfig(root=tmp_path, poll_s=0.05, recon=RECON), log=(lines := []).append)
    q = worker.queue
    (tmp_path / "s" / "recon").mkdir(parents=True)
    given_back(q, note(tmp_path / "s" / "recon", clock["now"] + DAY), "a-fast")
    for _ in range(2):
        doubts: list = []
        assert q.room_wait(None, doubts) is None
        worker._say_doubts(doubts)
    assert lines == [f"a-fast went back to the queue on a full disk, but its wait for room begins at "
                     f"{disk_room.when_text(clock['now'] + DAY)}, more than {ROOM_SKEW_S:.0f} s ahead of this "
                     f"machine's clock (a clock running ahead, or a damaged record): not waited for"], lines
    assert q.claim().job.id == "a-fast"
    ahead = note(tmp_path, clock["now"] + ROOM_SKEW_S / 2)  # within the clocks' skew: waited for
    assert RoomWait.from_note(ahead) is not None


def test_a_need_larger_than_the_whole_filesystem_is_waited_for_on_its_timer(tmp_path, monkeypatch):
    clock = clocks(monkeypatch)
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: PAGE)
    (tmp_path / "s" / "recon").mkdir(parents=True)
    huge = total_bytes(tmp_path) + 1
    wait = RoomWait.from_note(note(tmp_path / "s" / "recon", clock["now"], need_bytes=huge),
                              roots={"root": tmp_path})
    assert wait.over() == (False, PAGE)
    assert wait.need is None and wait.note()["need_bytes"] is None, "no room made can meet it: not said as awaited"
    clock["now"] += 600.0
    assert wait.over()[0]


def test_a_workers_own_wait_ends_on_the_monotonic_clock_whatever_the_wall_clock_does(tmp_path, monkeypatch):
    """Before: the wall clock alone ended it, so a clock set back two hours (by hand, or a first NTP step) held the
    worker two hours more."""
    clock = clocks(monkeypatch)
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: PAGE)
    wait = RoomWait.begin(tmp_path, held=0, retry_s=600.0)
    since = wait.since_unix
    clock["now"] -= 2 * 3600.0  # set back
    clock["monotonic"] += 599.0
    assert not wait.over()[0]
    clock["monotonic"] += 1.0
    assert wait.over()[0], "its 10 min are up"
    assert wait.note()["since_unix"] == since and wait.note()["retry_unix"] == since + 600.0, "the shared times"


def test_the_folder_is_found_under_the_readers_own_root(tmp_path, monkeypatch):
    """The worker that met the full disk ran on a machine with the captures at /a/caps; the reader mounts them at
    /b/caps, where the room has been made. Before: the reader probed /a/caps/s/recon, which here is another
    filesystem (its nearest existing parent), still full."""
    a, b = tmp_path / "a" / "caps", tmp_path / "b" / "caps"
    (b / "s" / "recon").mkdir(parents=True)
    probed: list[Path] = []

    def free(folder):
        probed.append(Path(folder))
        return 10**12 if b in Path(folder).parents else PAGE

    monkeypatch.setattr(disk_room, "free_bytes", free)
    written = RoomWait.begin(a / "s" / "recon", held=0, retry_s=600.0, roots={"root": a, "queue": a / ".queue"})
    assert written.note()["relative_to"] == "root" and written.note()["relative"] == "s/recon"
    reader = Queue(b / ".queue", root=b)
    given_back(reader, written.note(), "s-fast")
    assert reader.claim().job.id == "s-fast", "room made where the reader finds the folder"
    assert probed[-1] == b / "s" / "recon", probed


@pytest.mark.parametrize("case", ["no root known", "older note", "leaves the root"])
def test_a_folder_not_found_under_the_readers_root_waits_on_its_timer(tmp_path, monkeypatch, case):
    """Where the reader cannot find the folder, its free space is unknown: the wait ends on its timer, not on the
    free space of whatever filesystem holds the writer's path here. Before: the writer's path was probed, and its
    room (here plenty, on this machine's disk) ended the wait at once."""
    clock = clocks(monkeypatch)
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: 10**12)
    (tmp_path / "s" / "recon").mkdir(parents=True)
    noted = note(tmp_path / "s" / "recon", clock["now"], mount="/mnt/caps-of-a")  # the writer's, not here
    if case == "older note":
        noted = {k: v for k, v in noted.items() if k not in ("relative_to", "relative")}
    elif case == "leaves the root":
        noted["relative"] = "../../etc"
    q = Queue(tmp_path / "q", root=None if case == "no root known" else tmp_path)
    given_back(q, noted, "a-fast")
    waiting = q.room_wait()
    assert waiting is not None and waiting[1]["free_bytes"] is None and waiting[1]["need_bytes"] is None, waiting
    assert q.claim() is None
    clock["now"] += 600.0
    assert q.claim().job.id == "a-fast"


@pytest.mark.parametrize("mount", ["as noted", "as noted, the folder gone", "another"])
def test_a_folder_outside_both_roots_is_probed_where_written_if_it_is_here_on_its_mount(tmp_path, monkeypatch,
                                                                                         mount):
    """A job's own scratch space ($TMPDIR, a cache) lies under neither root: its note names no relative folder.
    Where that folder is here, on the filesystem the note says, room made there ends the wait. Before: the wait was
    unresolved and held every claim on every machine until its timer, room made or not."""
    clock = clocks(monkeypatch)
    free = {"now": PAGE}
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: free["now"])
    cache = tmp_path / "cache" / "job-tmp"
    cache.mkdir(parents=True)
    noted = {k: v for k, v in note(cache, clock["now"]).items() if k not in ("relative_to", "relative")}
    noted["mount"] = str(mount_point(cache)) if mount.startswith("as noted") else "/mnt/cache-of-a"
    if mount.endswith("gone"):  # a job's own temporary folder, removed as the job ended
        cache.rmdir()
    q = Queue(tmp_path / "caps" / ".queue", root=tmp_path / "caps")
    given_back(q, noted, "a-fast")
    assert q.claim() is None, "still full"
    free["now"] = 10**12
    if mount == "another":  # another machine's folder of that name: its room is not known here
        assert q.room_wait()[1]["free_bytes"] is None and q.claim() is None
        clock["now"] += 600.0
    assert q.claim().job.id == "a-fast"


def test_an_adopted_wait_ends_once_its_job_leaves_the_queue(tmp_path, monkeypatch, arun):
    """Worker B waits for the room worker A's job went back to the queue on; the operator then removes that job.
    Before: B waited on, claiming nothing for up to an hour, while a claim would have succeeded."""
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: PAGE)  # the disk stays full
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=tmp_path, poll_s=0.05, recon=RECON), log=lines.append)
    (tmp_path / "s" / "recon").mkdir(parents=True)
    given_back(worker.queue, note(tmp_path / "s" / "recon", time.time()), "a-fast")
    claims: list[int] = []
    monkeypatch.setattr(worker.queue, "claim", lambda *args: claims.append(1))  # (returns None: no job is started)
    arun(worker._poll_queue())
    assert worker.room is not None and worker.room.job == "a-fast" and not claims, lines
    (worker.queue.path / "queued" / "a-fast.json").unlink()  # removed by the operator
    arun(worker._poll_queue())
    assert worker.room is None and claims == [1], lines
    assert lines[-1] == "a-fast waits for room in the queue no more (claimed, settled or removed): claiming jobs again"


def test_an_adopted_wait_follows_the_next_job_that_holds_the_queue(tmp_path, monkeypatch, arun):
    """Two jobs went back on a full disk: once the one adopted leaves the queue, the other still holds every claim,
    and is the wait said."""
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: PAGE)
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=tmp_path, poll_s=0.05, recon=RECON), log=lines.append)
    claims: list[int] = []
    (tmp_path / "s" / "recon").mkdir(parents=True)
    given_back(worker.queue, note(tmp_path / "s" / "recon", time.time()), "a-fast", "b-fast")
    monkeypatch.setattr(worker.queue, "claim", lambda *args: claims.append(1))
    arun(worker._poll_queue())
    first = worker.room.job
    (worker.queue.path / "queued" / f"{first}.json").unlink()
    arun(worker._poll_queue())
    assert worker.room is not None and worker.room.job != first and not claims, lines
    said = f"waiting for room on {mount_point(tmp_path)} before claiming another job: {worker.room.job} went back"
    assert lines[-1].startswith(said), lines
