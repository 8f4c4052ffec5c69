"""Room on a worker's disk: how much is free where a job writes, where that filesystem is mounted, which of the
folders a job writes into met a full disk (`full_folder`), and the wait for room after a job met a full disk
(`RoomWait`), during which the worker claims no job (pool.py). A wait is also written down (`RoomWait.note`): in the
attempt record of the job it gave back, so that no worker claims a job while room is still missing (queue.py), and
in the worker's presence file (presence.py)."""

from __future__ import annotations

import math
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


def same_filesystem(a, b) -> bool:
    """Whether the folders `a` and `b` (or their nearest parents that exist) are on one filesystem; False where
    either cannot be asked."""
    try:
        return _device(a) == _device(b)
    except OSError:
        return False


def _device(folder) -> int:
    """The filesystem that holds `folder` (its nearest parent that exists), as its st_dev."""
    return os.stat(_existing(folder)).st_dev


def full_folder(exc: OSError, written) -> Path:
    """The folder whose filesystem the full-disk error `exc` met: the folder of the file it names; where it names
    none (numpy's short write, a write to a log through an inherited descriptor), that one of the folders `written`
    (where the process writes, its results' folder first) whose filesystem has the least room: the first where they
    share one or none can be asked."""
    if exc.filename:
        return Path(os.fsdecode(exc.filename)).parent
    written = [Path(folder) for folder in written]
    best, least, seen = written[0], math.inf, set()
    for folder in written:
        try:
            device = _device(folder)
            free = math.inf if device in seen else free_bytes(folder)
        except OSError:
            continue
        seen.add(device)
        if free < least:
            best, least = folder, free
    return best


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
    otherwise hold the worker for good. A full quota (EDQUOT) is one user's, which the filesystem's free space does
    not show: that wait ends on its timer alone (`quota`), as does one whose free space could not be asked.

    Its times are the clock's (time.time), not a monotonic one's: other workers read them (`note`)."""

    folder: Path
    """The folder that could not be written."""
    mount: Path
    """Where the filesystem that holds it is mounted."""
    free: int | None
    """Bytes free when last probed (when the wait began, then at each `over`); None where it could not be asked."""
    need: int | None
    """Bytes free that end the wait; None where only its timer ends it (a quota, free space that cannot be asked)."""
    retry_s: float
    """Seconds after which the wait ends all the same."""
    since_unix: float
    """When the wait began (time.time)."""
    quota: bool = False
    """The job met a full disk quota (EDQUOT), not a full filesystem."""
    job: str | None = None
    """The job that met the full disk, when known."""

    @classmethod
    def begin(cls, folder, held: int, retry_s: float, *, quota: bool = False, job: str | None = None) -> "RoomWait":
        """The wait after a job whose partial result took `held` bytes met a full disk writing into `folder`,
        that result removed (OSError when the free space cannot be asked)."""
        free = free_bytes(folder)
        need = None if quota else free + max(held, ROOM_MARGIN)
        return cls(Path(folder), mount_point(folder), free, need, retry_s, time.time(), quota, job)

    @classmethod
    def unasked(cls, folder, retry_s: float, *, quota: bool = False, job: str | None = None) -> "RoomWait":
        """The wait on `folder` whose free space cannot be asked (a lost mount): its timer alone ends it."""
        return cls(Path(folder), mount_point(folder), None, None, retry_s, time.time(), quota, job)

    @property
    def retry_unix(self) -> float:
        """When the wait ends all the same (time.time)."""
        return self.since_unix + self.retry_s

    def timed_out(self, now: float | None = None) -> bool:
        return (time.time() if now is None else now) >= self.retry_unix

    def over(self) -> tuple[bool, int]:
        """(whether the wait is over, the bytes free now): the room it waits for is there, or `retry_s` has passed.
        One statvfs (OSError when it cannot be asked)."""
        free = self.free = free_bytes(self.folder)
        return (self.need is not None and free >= self.need) or self.timed_out(), free

    def note(self) -> dict:
        """The wait as others read it (a worker's presence file, the attempt record of the job it gave back): exactly
        the keys mount, folder (str), free_bytes, need_bytes (int or None), since_unix, retry_unix (float), quota."""
        return {"mount": str(self.mount), "folder": str(self.folder), "free_bytes": self.free,
                "need_bytes": self.need, "since_unix": float(self.since_unix), "retry_unix": float(self.retry_unix),
                "quota": bool(self.quota)}

    @classmethod
    def from_note(cls, note, job: str | None = None) -> "RoomWait | None":
        """The wait a `note` describes, or None when it is not one (a damaged or hand-edited record)."""
        try:
            mount, folder, quota = note["mount"], note["folder"], note["quota"]
            free, need = _count(note["free_bytes"]), _count(note["need_bytes"])
            since, until = _instant(note["since_unix"]), _instant(note["retry_unix"])
        except (KeyError, TypeError, ValueError):
            return None
        if not (isinstance(mount, str) and isinstance(folder, str) and isinstance(quota, bool)) or until < since:
            return None
        return cls(Path(folder), Path(mount), free, need, until - since, since, quota, job)

    def begun_line(self, poll_s: float) -> str:
        """What the worker whose job met the full disk says when its wait begins."""
        if self.quota:
            return (f"waiting for room in the disk quota on {self.mount} before claiming another job: a full quota "
                    f"does not show in the free space ({_free_text(self.free)} free), so no probe can tell when room "
                    f"is made: claiming again in {self.retry_s / 60:.0f} min")
        return (f"waiting for room on {self.mount} before claiming another job: {_free_text(self.free)} free, the job "
                f"needs more (waiting for {_free_text(self.need)}, checked every {poll_s:g} s; claiming again in "
                f"{self.retry_s / 60:.0f} min all the same)")

    def adopted_line(self, poll_s: float) -> str:
        """What a worker says that waits for the room another one's job (`job`) waits for (`Queue.room_wait`)."""
        if self.quota:
            needs = "a full disk quota there, which no probe of the free space shows"
        elif self.need is not None:
            needs = (f"a full disk there ({_free_text(self.free)} free when it did, waiting for "
                     f"{_free_text(self.need)}, checked every {poll_s:g} s)")
        else:
            needs = "a full disk there, whose free space could not be checked"
        left = max(0.0, self.retry_unix - time.time())
        return (f"waiting for room on {self.mount} before claiming another job: {self.job} went back to the queue on "
                f"{needs}; claiming again in {left / 60:.0f} min all the same")

    def ended_line(self, free: int | None) -> str:
        """What a worker says when its wait ends with `free` bytes free (None: not known): room is there, or its time
        is up."""
        if self.need is not None and free is not None and free >= self.need:
            return f"room again on {self.mount} ({size_text(free)} free): claiming jobs again"
        if self.quota:
            return (f"waited {self.retry_s / 60:.0f} min for room in the disk quota on {self.mount}: claiming jobs "
                    f"again, in case room was made")
        if self.need is None or free is None:
            return (f"waited {self.retry_s / 60:.0f} min for room on {self.mount}, whose free space could not be "
                    f"checked: claiming jobs again")
        return (f"still {size_text(free)} free on {self.mount} after {self.retry_s:.0f} s, less than the "
                f"{size_text(self.need)} waited for: claiming jobs again, in case that is room enough")


def room_missing(note, now: float | None = None) -> bool:
    """Whether the room a job given back on a full disk waits for (its record's `room`, `RoomWait.note`) is still
    missing: its retry time has not come and its filesystem has not the room it needs (one statvfs; a quota's, or
    one that cannot be asked, waits for its time). A note that is not one waits for nothing."""
    wait = RoomWait.from_note(note)
    if wait is None or wait.timed_out(now):
        return False
    try:
        return not wait.over()[0]
    except OSError:
        return True


def _free_text(free: int | None) -> str:
    return "an unknown amount" if free is None else size_text(free)


def _count(value) -> int | None:
    """A note's byte count: an int >= 0 or None (ValueError otherwise)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(value)
    return value


def _instant(value) -> float:
    """A note's time: a finite number (ValueError otherwise)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(value)
    return float(value)


def retry_after(full_in_row: int) -> float:
    """`RoomWait.retry_s` for the `full_in_row`-th full disk since a job last finished (1 for the first)."""
    return min(ROOM_RETRY_S * 2 ** max(full_in_row - 1, 0), ROOM_RETRY_MAX_S)


__all__ = ["MAX_FULL_DISK", "free_bytes", "mount_point", "same_filesystem", "full_folder", "folder_bytes", "size_text",
           "ROOM_MARGIN", "ROOM_RETRY_S", "ROOM_RETRY_MAX_S", "RoomWait", "room_missing", "retry_after"]
