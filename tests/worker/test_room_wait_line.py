"""A wait for room in one line (disk_room.room_line, room_said), the one wording that `spadscan ctl` (of a queued job
while every worker waits for room) and the dashboard use: places and figures as the worker's own lines say them
(RoomWait.where, .figures), times as `worker --status` says them (when_text)."""

from __future__ import annotations

import time

from spadscan.worker.disk_room import (ROOM_RETRY_MAX_S, RoomWait, held_said, holding_said, names_said, room_line,
                                        room_said, when_text)

MB = 1_000_000


def note(mount: str = "/mnt/scratch", free: int | None = 12 * MB, need: int | None = 40 * MB,
         retry_in_s: float = 600.0, quota: bool = False, **fields) -> dict:
    now = time.time()
    return {"mount": mount, "folder": f"{mount}/caps/q1/recon", "free_bytes": free, "need_bytes": need,
            "since_unix": now - 5.0, "retry_unix": now + retry_in_s, "quota": quota, **fields}


def test_the_line_says_each_disk_once_what_to_do_and_by_when():
    later, quota = note(retry_in_s=1800.0), note("/data", None, None, 300.0, True)
    assert room_said([later, quota]) == (
        f"every worker (2) waits for room on /mnt/scratch (12 MB free, 40 MB needed) and in the disk quota on /data "
        f"(free space unknown): make room there or raise the quota; a worker claims again by "
        f"{when_text(quota['retry_unix'])} (sooner once there is room)")
    bounded = note(retry_unix=1e300)
    assert room_said([bounded]).endswith(f"by {when_text(bounded['since_unix'] + ROOM_RETRY_MAX_S)} (sooner once "
                                         f"there is room)")


def test_a_time_that_cannot_be_said_is_left_out():
    wait = RoomWait.from_note(note())
    assert room_line("mug-fast waits", [wait], "a worker", None) == (
        "mug-fast waits for room on /mnt/scratch (12 MB free, 40 MB needed): make room there")
    assert room_line("mug-fast waits", [wait], "a worker", 1e300).endswith(": make room there")


def test_every_disk_that_holds_the_queue_is_named():
    """Every worker waits on /mnt/scratch, and a queued job's wait on /data holds every claim: both are where room
    is missing. Before: /data was used for the time only, never named."""
    worker, queued = note(retry_in_s=300.0), note("/data", 1 * MB, 900 * MB, 1800.0)
    assert room_said([worker], [queued]) == (
        f"the worker waits for room on /mnt/scratch (12 MB free, 40 MB needed) and on /data (1.0 MB free, 900 MB "
        f"needed): make room there; it claims again by {when_text(queued['retry_unix'])} (sooner once there is room)")


def test_a_full_disk_and_a_full_quota_on_one_mount_are_both_said_in_either_order():
    """Before: one mount was said once, the first wait's (a quota or a full filesystem, by the workers' order)."""
    full, quota = note("/data", retry_in_s=300.0), note("/data", None, None, 900.0, True)
    places = "on /data (12 MB free, 40 MB needed)", "in the disk quota on /data (free space unknown)"
    tail = (f": make room there or raise the quota; a worker claims again by {when_text(full['retry_unix'])} (sooner "
            f"once there is room)")
    assert room_said([full, quota]) == f"every worker (2) waits for room {places[0]} and {places[1]}{tail}"
    assert room_said([quota, full]) == f"every worker (2) waits for room {places[1]} and {places[0]}{tail}"


def test_a_time_not_after_now_is_left_out():
    """A worker whose clock is behind, or a presence file its worker no longer renews, notes a retry already past:
    no promise to make. Before: 'it claims again by' a time gone."""
    past = note(retry_in_s=-120.0, since_unix=time.time() - 720.0)
    assert room_said([past]) == "the worker waits for room on /mnt/scratch (12 MB free, 40 MB needed): make room there"
    wait = RoomWait.from_note(note())
    assert room_line("x waits", [wait], "a worker", wait.retry_unix, now=wait.retry_unix).endswith("make room there")
    assert room_line("x waits", [wait], "a worker", wait.retry_unix, now=wait.retry_unix - 1.0).endswith(
        "(sooner once there is room)")


def test_a_held_queue_with_no_worker_says_to_start_one():
    """A queued job's wait holds every claim and no worker is present: the line says to start one, then when a claim
    can succeed at the earliest. Before: the wait alone, with 'a worker claims again' and no worker to."""
    held = note("/data", 1 * MB, 900 * MB, 1800.0)
    by = f"; a worker claims again by {when_text(held['retry_unix'])} (sooner once there is room)"
    before = f"; no claim succeeds before {when_text(held['retry_unix'])} (sooner once there is room)"
    said = "no job is claimed while mug-fast waits for room on /data (1.0 MB free, 900 MB needed): make room there"
    start = "spadscan worker --root /caps"
    assert held_said([("mug-fast", held)], present=0, start=start) == (
        f"{said}; no worker is running: start one with `{start}`{before}")
    assert holding_said([], [("mug-fast", held)], 0, start=start) == held_said([("mug-fast", held)], (), 0,
                                                                                 start=start)
    assert held_said([("mug-fast", held)], present=1, start=start) == said + by  # a worker is there: no start


def test_a_waiting_workers_disk_is_not_laid_to_the_held_jobs():
    """Two jobs hold the queue on /data and the one worker waits on /mnt/scratch: the jobs' disk is theirs, the
    worker's said as its. Before: 'mug-fast, cup-fast wait for room on /data (...) and on /mnt/scratch (...)'."""
    data = note("/data", 1 * MB, 900 * MB, 1800.0)
    said = held_said([("mug-fast", data), ("cup-fast", data)], [note()], present=1)
    assert said.startswith("no job is claimed while mug-fast, cup-fast wait for room on /data (1.0 MB free, 900 MB "
                           "needed); a worker waits for room on /mnt/scratch (12 MB free, 40 MB needed): make room "
                           "there; a worker claims again by "), said
    same = held_said([("mug-fast", data)], [note("/data", 1 * MB, 900 * MB)], present=1)
    assert "a worker waits" not in same, "a worker waiting on the jobs' own disk adds nothing"


def test_only_the_notes_read_count():
    """A damaged note is no wait. Before: room_said([{'mount': 3}]) said 'the worker waits for room : make room
    there', and a damaged note among others counted as one more worker."""
    damaged = {"mount": 3}
    assert room_said([damaged]) is None and room_said([]) is None
    assert room_said([damaged, note()]).startswith("the worker waits for room on /mnt/scratch (12 MB free")
    assert holding_said([damaged], [], 1) is None  # the caller says its usual line
    assert held_said([("mug-fast", damaged)]) is None


def test_one_helper_names_things_in_a_line_for_every_message():
    """names_said: ctl's and the dashboard's jobs and workers (commas), the captures and chunks a refused folder
    names ("and" before the last), a sensor's zones (all of them)."""
    assert names_said(["a", "b", "c"]) == "a, b, c" and names_said(list("abcde")) == "a, b, c and 2 more"
    assert names_said(["a"], last_and=True) == "a" and names_said(["a", "b"], last_and=True) == "a and b"
    assert names_said(["a", "b", "c"], last_and=True) == "a, b and c"
    assert names_said(list("abcde"), last_and=True) == "a, b, c and 2 more"
    assert names_said(list("abcde"), last_and=True, most=None) == "a, b, c, d and e"
    assert names_said([], last_and=True) == ""
