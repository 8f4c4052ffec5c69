"""Room on a worker's disk: how much is free where a job writes, where that filesystem is mounted, and the wait for
room after a job met a full disk (`RoomWait`), during which the worker claims no job (pool.py)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path


def _existing(folder) -> Path:
    """`folder` (made absolute), or its nearest parent that exists (a result folder removed meanwhile)."""
    path = Path(os.path.abspath(folder))
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def free_bytes(folder) -> int:
    """Bytes an ordinary user may still write on the filesystem that holds `folder` (statvfs; OSError when it
    cannot be asked: a lost mount)."""
    st = os.statvfs(_existing(folder))
    return st.f_bavail * st.f_frsize


def mount_point(folder) -> Path:
    """The folder where the filesystem that holds `folder` is mounted: what a user makes room on (`folder` itself
    where the file system cannot be asked: a lost mount, a folder this user may not read)."""
    try:
        path = _existing(folder)
        while not os.path.ismount(path) and path != path.parent:
            path = path.parent
    except OSError:
        return Path(os.path.abspath(folder))
    return path


def folder_bytes(folder) -> int:
    """Bytes of disk the files under `folder` take (their blocks, not their lengths); 0 when it is gone."""
    total = 0
    try:
        for path in Path(folder).rglob("*"):
            try:
                st = path.lstat()
            except OSError:
                continue
            total += st.st_blocks * 512
    except OSError:  # a folder that cannot be listed: what was counted
        pass
    return total


def size_text(n: int) -> str:
    """Bytes for a person: '300 kB', '1.3 MB', '12 GB' (powers of 1000, as df -H)."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            value = n / scale
            return f"{value:.1f} {unit}" if value < 10 else f"{value:.0f} {unit}"
    return f"{n} bytes"


ROOM_MARGIN = 1 << 20
"""Bytes (1 MiB) more than it had that a job that met a full disk is given at least before it runs again."""
MAX_FULL_DISK = 3
"""A job that met a full disk this many times fails (counted then: `spadscan worker --retry-failed` queues it again):
its result may need more room than the disk ever frees, and every run of it fills the disk again for every other
writer on it (the daemon's captures among them)."""
ROOM_RETRY_S = 600.0
ROOM_RETRY_MAX_S = 3600.0
"""Seconds after which a wait for room ends even without the room it waited for (`RoomWait`): 10 min for the first
full disk in a row, doubling with each next one, at most an hour."""


@dataclass
class RoomWait:
    """A worker's wait for room on a full disk before it claims another job.

    The worker probes the free space (statvfs, at every poll) rather than retrying the job after a growing delay: a
    retry runs the job's whole set-up and training (minutes) only to meet the full disk again, while a probe costs
    nothing and sees room the moment it is made. The job needs more than it had: the wait ends once more is free
    than after its partial result was removed, by as much again as that result took (at least ROOM_MARGIN). How
    much more the job would have written is not known, so that is a guess, and the wait also ends after `retry_s`
    (`retry_after`): room freed elsewhere just as the job ended (another job's partial result, removed first) would
    otherwise hold the worker for good."""

    folder: Path
    """The folder that could not be written."""
    mount: Path
    """Where the filesystem that holds it is mounted."""
    free: int
    """Bytes free when the wait began."""
    need: int
    """Bytes free that end the wait."""
    retry_s: float
    """Seconds after which the wait ends all the same."""
    began: float
    """When the wait began (time.monotonic)."""

    @classmethod
    def begin(cls, folder, held: int, retry_s: float) -> "RoomWait":
        """The wait after a job whose partial result took `held` bytes met a full disk writing into `folder`,
        that result removed (OSError when the free space cannot be asked)."""
        free = free_bytes(folder)
        return cls(Path(folder), mount_point(folder), free, free + max(held, ROOM_MARGIN), retry_s, time.monotonic())

    def over(self) -> tuple[bool, int]:
        """(whether the wait is over, the bytes free now): the room it waits for is there, or `retry_s` has passed."""
        free = free_bytes(self.folder)
        return free >= self.need or time.monotonic() - self.began >= self.retry_s, free


def retry_after(full_in_row: int) -> float:
    """`RoomWait.retry_s` for the `full_in_row`-th full disk since a job last finished (1 for the first)."""
    return min(ROOM_RETRY_S * 2 ** max(full_in_row - 1, 0), ROOM_RETRY_MAX_S)


__all__ = ["MAX_FULL_DISK", "free_bytes", "mount_point", "folder_bytes", "size_text", "ROOM_MARGIN", "ROOM_RETRY_S",
           "ROOM_RETRY_MAX_S", "RoomWait", "retry_after"]
