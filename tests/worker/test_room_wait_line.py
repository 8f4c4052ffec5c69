"""A wait for room in one line (disk_room.room_line, room_said), the one wording that `spadscan ctl` (of a queued job
while every worker waits for room) and the dashboard use: places and figures as the worker's own lines say them
(RoomWait.where, .figures), times as `worker --status` says them (when_text)."""

from __future__ import annotations

import time

from spadscan.worker.disk_room import ROOM_RETRY_MAX_S, RoomWait, room_line, room_said, when_text

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
