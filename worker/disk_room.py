"""Room on a worker's disk: how much is free where a job writes, where that filesystem is mounted, which of the
folders a job writes into met a full disk (`full_folder`), and the wait for room after a job met a full disk
(`RoomWait`), during which the worker claims no job (pool.py). A wait is also written down (`RoomWait.note`): in the
attempt record of the job it gave back, so that no worker claims a job while room is still missing (queue.py), and
in the worker's presence file (presence.py).

A wait others read names its folder twice: as the writer's absolute path, and relative to the queue or the captures
root (`relative_to`, `relative`), which the reader resolves under its own (`from_note`'s `roots`): a second machine
may mount the captures elsewhere, where the writer's path names another filesystem or none. Its times are the wall
clock's, which machines share; a wait of this process's own ends on the monotonic clock as well (`deadline`), which
a clock set back does not lengthen. A note is bounded as it is read: a wait never runs past the longest a worker
waits (ROOM_RETRY_MAX_S), and one that begins ahead of the reader's clock by more than ROOM_SKEW_S is none
(`note_doubt` says why)."""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path, PurePosixPath


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


def total_bytes(folder) -> int:
    """Bytes the filesystem that holds `folder` has in all (statvfs; OSError when it cannot be asked)."""
    st = os.statvfs(_existing(folder))
    return st.f_blocks * st.f_frsize


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
ROOM_SKEW_S = 60.0
"""Seconds a wait noted on another machine may begin ahead of this one's clock: machines sharing a queue keep their
clocks within a few seconds (NTP). One further ahead comes from a clock running ahead or a damaged record: waiting
for it would hold every claim until that clock's time comes, so it is not waited for."""
ROOTS = ("queue", "root")
"""What a wait's folder is noted relative to (`RoomWait.relative`), in the order tried: the queue, which every
reader of a note reads, then the captures root."""


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

    Its times are the wall clock's (time.time), which other workers read (`note`); this process's own wait also ends
    at its `deadline` on the monotonic clock, which a wall clock set back does not move."""

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
    deadline: float | None = None
    """When this process's wait ends all the same on the monotonic clock (time.monotonic), whatever the wall clock
    does meanwhile; None: only `retry_unix` ends it."""
    relative: tuple[str, str] | None = None
    """`folder` as others find it: (one of ROOTS, the folder relative to it, '/'-separated); None where it lies under
    neither (its readers wait on its timer)."""
    unresolved: bool = False
    """Read from a note whose folder could not be found on this machine (`from_note`'s `roots`): its free space is
    not known here, and its timer alone ends it."""

    @classmethod
    def begin(cls, folder, held: int, retry_s: float, *, quota: bool = False, job: str | None = None,
              roots: dict | None = None) -> "RoomWait":
        """The wait after a job whose partial result took `held` bytes met a full disk writing into `folder`,
        that result removed (OSError when the free space cannot be asked). `roots`: {"queue": the queue's folder,
        "root": the captures root}, which its note names the folder relative to."""
        free = free_bytes(folder)
        need = None if quota else free + max(held, ROOM_MARGIN)
        return cls(Path(folder), mount_point(folder), free, need, retry_s, time.time(), quota, job,
                   time.monotonic() + retry_s, _relative(folder, roots or {}))

    @classmethod
    def unasked(cls, folder, retry_s: float, *, quota: bool = False, job: str | None = None,
                roots: dict | None = None) -> "RoomWait":
        """The wait on `folder` whose free space cannot be asked (a lost mount): its timer alone ends it."""
        return cls(Path(folder), mount_point(folder), None, None, retry_s, time.time(), quota, job,
                   time.monotonic() + retry_s, _relative(folder, roots or {}))

    @property
    def retry_unix(self) -> float:
        """When the wait ends all the same (time.time)."""
        return self.since_unix + self.retry_s

    def timed_out(self, now: float | None = None) -> bool:
        """Whether the wait's time is up: at `retry_unix` by the wall clock (`now`: its reading), or, for this
        process's own wait read without `now`, at its monotonic `deadline`, whichever comes first."""
        if (time.time() if now is None else now) >= self.retry_unix:
            return True
        return now is None and self.deadline is not None and time.monotonic() >= self.deadline

    def over(self) -> tuple[bool, int | None]:
        """(whether the wait is over, the bytes free now): the room it waits for is there, or `retry_s` has passed.
        One statvfs (OSError when it cannot be asked); none for a wait whose folder is not on this machine
        (`unresolved`: free None). A need larger than the whole filesystem can never be met: its timer ends it."""
        if self.unresolved:
            return self.timed_out(), None
        free = self.free = free_bytes(self.folder)
        if self.need is not None and self.need > _total_or(self.folder, self.need):
            self.need = None  # (a damaged note, or one about another filesystem): waited for on its timer
        return (self.need is not None and free >= self.need) or self.timed_out(), free

    def note(self) -> dict:
        """The wait as others read it (a worker's presence file, the attempt record of the job it gave back): the
        keys mount, folder (str), free_bytes, need_bytes (int or None), since_unix, retry_unix (float), quota, and,
        where the folder lies under the queue or the captures root, relative_to ("queue" or "root") and relative
        (str: the folder relative to it)."""
        shown = {"mount": str(self.mount), "folder": str(self.folder), "free_bytes": self.free,
                 "need_bytes": self.need, "since_unix": float(self.since_unix), "retry_unix": float(self.retry_unix),
                 "quota": bool(self.quota)}
        if self.relative is not None:
            shown["relative_to"], shown["relative"] = self.relative
        return shown

    @classmethod
    def from_note(cls, note, job: str | None = None, *, now: float | None = None, roots: dict | None = None,
                  skewed: bool = False) -> "RoomWait | None":
        """The wait a `note` describes, or None when it is not one (a damaged or hand-edited record) or begins more
        than ROOM_SKEW_S ahead of this machine's clock (`now`: its reading). A wait noted to run longer than
        ROOM_RETRY_MAX_S (the longest a worker waits) runs that long from its start (`note_doubt` says both).
        `roots` ({"queue", "root"}: this machine's folders): the folder is found under them (`relative`), where its
        free space is asked; one under neither is asked where the note names it, if that folder is here on the
        noted mount; one found nowhere is `unresolved`, its free space unknown. Without `roots` the note is only
        read (to be said), as it stands. `skewed`: one ahead of this clock is read all the same (to be said: the
        skew matters only to the queue's gate, while its worker does wait)."""
        try:
            mount, folder, quota = note["mount"], note["folder"], note["quota"]
            free, need = _count(note["free_bytes"]), _count(note["need_bytes"])
            since, until = _instant(note["since_unix"]), _instant(note["retry_unix"])
        except (KeyError, TypeError, ValueError):
            return None
        if not (isinstance(mount, str) and isinstance(folder, str) and isinstance(quota, bool)) or until < since:
            return None
        now = time.time() if now is None else now
        if since > now + ROOM_SKEW_S and not skewed:
            return None
        retry_s = min(until - since, ROOM_RETRY_MAX_S)
        left = min(max(since + retry_s - now, 0.0), ROOM_RETRY_MAX_S)
        wait = cls(Path(folder), Path(mount), free, need, retry_s, since, quota, job, time.monotonic() + left,
                   _noted_relative(note))
        return wait if roots is None else wait._found(roots)

    def _found(self, roots: dict) -> "RoomWait":
        """This wait with its folder as found under this machine's `roots`; else as written, where that folder is
        here on the filesystem mounted where the note says (a full $TMPDIR or cache, outside both roots: on the
        writer's own machine, room made there ends the wait); `unresolved` otherwise."""
        local = _resolve(self.relative, roots)
        if local is not None:
            return replace(self, folder=local, mount=mount_point(local))
        if _here(self.folder, self.mount):
            return self
        return replace(self, free=None, need=None, unresolved=True)

    @property
    def where(self) -> str:
        """Where room is waited for, as every line about the wait says it: 'on /data', 'in the disk quota on
        /data'."""
        return f"in the disk quota on {self.mount}" if self.quota else f"on {self.mount}"

    @property
    def figures(self) -> str:
        """Its bytes, as the lines about every worker's waits say them: '12 MB free, 40 MB needed', 'free space
        unknown'."""
        free = "free space unknown" if self.free is None else f"{size_text(self.free)} free"
        return free if self.need is None else f"{free}, {size_text(self.need)} needed"

    def begun_line(self, poll_s: float) -> str:
        """What the worker whose job met the full disk says when its wait begins."""
        if self.quota:
            return (f"waiting for room {self.where} before claiming another job: a full quota "
                    f"does not show in the free space ({_free_text(self.free)} free), so no probe can tell when room "
                    f"is made: claiming again in {self.retry_s / 60:.0f} min")
        return (f"waiting for room {self.where} before claiming another job: {_free_text(self.free)} free, the job "
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
        return (f"waiting for room {self.where} before claiming another job: {self.job} went back to the queue on "
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


def missing_room(note, now: float | None = None, roots: dict | None = None) -> RoomWait | None:
    """The wait a job given back on a full disk is in (its record's `room`, `RoomWait.note`, read under this
    machine's `roots`: `RoomWait.from_note`) while its room is still missing: its retry time has not come and its
    filesystem has not the room it needs (one statvfs; a quota's, one that cannot be asked, and one whose folder is
    not found under `roots` wait for their time). None when it is not missing; a note that is not one waits for
    nothing."""
    wait = RoomWait.from_note(note, now=now, roots=roots if roots is not None else {})
    if wait is None or wait.timed_out(now):
        return None
    try:
        return None if wait.over()[0] else wait
    except OSError:
        return wait


def room_missing(note, now: float | None = None, roots: dict | None = None) -> bool:
    """Whether the room a noted wait waits for is still missing (`missing_room`)."""
    return missing_room(note, now, roots) is not None


def note_doubt(note, now: float | None = None) -> str | None:
    """Why a noted wait (`RoomWait.note`) is not waited for as it says, in a few words, or None: it begins more than
    ROOM_SKEW_S ahead of this machine's clock (`now`: its reading), or runs longer than any worker waits."""
    try:
        since, until = _instant(note["since_unix"]), _instant(note["retry_unix"])
    except (KeyError, TypeError, ValueError):
        return None
    now = time.time() if now is None else now
    if since > now + ROOM_SKEW_S:
        return (f"its wait for room begins at {when_text(since)}, more than {ROOM_SKEW_S:.0f} s ahead of this "
                f"machine's clock (a clock running ahead, or a damaged record): not waited for")
    if until - since > ROOM_RETRY_MAX_S:
        return (f"its wait for room runs {(until - since) / 60:.0f} min, longer than any worker waits: waited for "
                f"{ROOM_RETRY_MAX_S / 60:.0f} min from its start at most")
    return None


UNKNOWN_TIME = "an unknown time"
"""`when_text` of a time past what the clock can name (a damaged file's)."""


def when_text(unix: float) -> str:
    """A time for a person, as every line about a wait (and `worker --status`) says it: '2025-03-01 14:05 UTC'
    (UNKNOWN_TIME for one past what the clock can name)."""
    try:
        return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(unix))
    except (OverflowError, OSError, ValueError):
        return UNKNOWN_TIME


def room_line(who: str, waits, claimer: str, by: float | None, *, now: float | None = None,
              start: str | None = None, also=(), also_who: str = "") -> str:
    """A wait for room in one line, as `spadscan ctl` and the dashboard say it: '{who} for room on /data (12 MB free,
    40 MB needed): make room there; {claimer} claims again by 2025-03-01 14:05 UTC (sooner once there is room)'.
    `waits` (RoomWait): each place said once, a full filesystem and a full quota on one mount being two (with the
    figures of the first wait that names it: `RoomWait.where`, `.figures`); `also`: more waits, whose places not
    among those are said after them as `also_who`'s ('; a worker waits for room on /scratch (...)'); `by` (unix
    seconds): when a claim succeeds again at the latest, as `when_text` says it, not said where None, past what the
    clock can name, or not after `now` (time.time(): a time already past, from a worker's clock behind or a note its
    worker no longer renews, is no promise). `start`: no worker is running, and this command starts one: said before
    the time, which is then when a claim can succeed at the earliest (no one claims before one is started)."""
    places = _places(waits)
    extra = {key: wait for key, wait in _places(also).items() if key not in places}
    said = _places_said(places) + (f"; {also_who} for room {_places_said(extra)}" if extra else "")
    quota = any(wait.quota for wait in [*places.values(), *extra.values()])
    fix = "make room there" + (" or raise the quota" if quota else "")
    now = time.time() if now is None else now
    when = UNKNOWN_TIME if by is None or not by > now else when_text(by)
    first = "" if start is None else f"; no worker is running: start one with `{start}`"
    promise = f"{claimer} claims again by" if start is None else "no claim succeeds before"
    again = "" if when == UNKNOWN_TIME else f"; {promise} {when} (sooner once there is room)"
    return f"{who} for room {said}: {fix}{first}{again}"


def _places(waits) -> dict:
    """{(mount, quota): the first wait that names it}: each place a wait is for, once."""
    places = {}
    for wait in waits:
        places.setdefault((wait.mount, wait.quota), wait)
    return places


def _places_said(places: dict) -> str:
    """'on /data (12 MB free, 40 MB needed) and in the disk quota on /home (...)': `_places`' each with its figures."""
    return " and ".join(f"{wait.where} ({wait.figures})" for wait in places.values())


def room_said(notes, queue_notes=(), *, now: float | None = None) -> str | None:
    """What a queued job waits for while every worker present waits for room (`notes`: their presence files'
    `room_wait`s, each read as it stands, one ahead of this clock too: its worker waits all the same), in one line
    (`room_line`): each disk the workers wait on and each that holds the queue (`queue_notes`: the waits of the queued
    jobs given back on a full disk whose room is still missing, `Queue.room_waits`), what to do, and by when a worker
    claims again at the latest: once the first of their own waits ends, and no sooner than the last of `queue_notes`
    (no claim succeeds before). Only the notes read count (a damaged one is no wait); None where none is read: the
    caller says what it says without a wait."""
    read = _read(notes)
    if not read:
        return None
    held = _read(queue_notes)
    by = max([min(wait.retry_unix for wait in read), *(wait.retry_unix for wait in held)])
    one = len(read) == 1
    return room_line("the worker waits" if one else f"every worker ({len(read)}) waits", read + held,
                     "it" if one else "a worker", by, now=now)


def held_said(held, notes=(), present: int = 1, *, start: str | None = None, now: float | None = None) -> str | None:
    """What holds the queue while a queued job's wait for room does (`held`: (job id, its wait) as `Queue.room_waits`
    gives them: no claim succeeds until the last of them ends or its room is made), in one line (`room_line`): the
    jobs, their disks and those of the workers that wait (`notes`: their `room_wait`s), what to do, and by when a
    worker claims again at the latest; where no worker is present (`present` 0), to start one with `start` (as
    `spadscan worker` where not given). None where no wait of `held` is read."""
    queued = [(job, wait) for job, wait in ((job, RoomWait.from_note(note, skewed=True)) for job, note in held)
              if wait is not None]
    if not queued:
        return None
    jobs = [job for job, _ in queued]
    who = f"no job is claimed while {names_said(jobs)} {'waits' if len(jobs) == 1 else 'wait'}"
    workers = _read(notes)
    return room_line(who, [wait for _, wait in queued], "a worker", max(wait.retry_unix for _, wait in queued),
                     now=now, start=None if present else (start or "spadscan worker"), also=workers,
                     also_who="a worker waits" if len(workers) == 1 else f"{len(workers)} workers wait")


def holding_said(notes, held, present: int, *, start: str | None = None, now: float | None = None) -> str | None:
    """What holds the queued jobs where room on a full disk does, in one line, as `spadscan ctl` says it of a queued
    live job and the dashboard of the queue: every worker present waits for room (`notes`: the `room_wait`s of the
    workers that wait, `present`: how many workers are present): `room_said`, the queue's waits (`held`: (job id, its
    wait), `Queue.room_waits`) bounding the time; else a queued job's wait holds every claim: `held_said` (`start`:
    the command that starts a worker, said where none is present). None where room holds nothing (a worker takes
    the jobs at its next look, or no worker is running and nothing else holds them)."""
    read = _read(notes)
    if read and len(read) == present:
        return room_said(notes, [note for _, note in held], now=now)
    return held_said(held, notes, present, start=start, now=now)


def _read(notes) -> list[RoomWait]:
    """The waits `notes` describe, each read as it stands (`RoomWait.from_note`, one ahead of this clock too); a
    note that is none (a damaged record) left out."""
    return [wait for wait in (RoomWait.from_note(note, skewed=True) for note in notes) if wait is not None]


NAMED = 3
"""How many names a line says before it counts the rest (`names_said`)."""


def names_said(items: list[str], last_and: bool = False, most: int | None = NAMED) -> str:
    """Names in a line, as `spadscan ctl` and the dashboard name jobs and workers: at most `most` (None: all), then
    how many more. `last_and`: the last two of those all named joined by "and" ("a, b and c"), not a comma."""
    if most is not None and len(items) > most:
        return ", ".join(items[:most]) + f" and {len(items) - most} more"
    if last_and and len(items) > 1:
        return f"{', '.join(items[:-1])} and {items[-1]}"
    return ", ".join(items)


def _relative(folder, roots: dict) -> tuple[str, str] | None:
    """(the first of ROOTS that `folder` lies under, the folder relative to it), or None: as the paths are written,
    else with their links resolved (a captures root named through a link)."""
    for name in ROOTS:
        base = roots.get(name)
        if base is None:
            continue
        for mine, theirs in ((os.path.abspath(folder), os.path.abspath(base)),
                             (os.path.realpath(folder), os.path.realpath(base))):
            try:
                return name, Path(mine).relative_to(theirs).as_posix()
            except ValueError:
                continue
    return None


def _noted_relative(note) -> tuple[str, str] | None:
    """A note's (relative_to, relative), or None where it names none or names it otherwise (a damaged record, an
    older worker's)."""
    under, relative = note.get("relative_to"), note.get("relative")
    if under in ROOTS and isinstance(relative, str):
        return under, relative
    return None


def _resolve(relative: tuple[str, str] | None, roots: dict) -> Path | None:
    """The folder `relative` names under this machine's `roots`, or None where it names none there (no such root
    here, a path that leaves it)."""
    if relative is None or roots.get(relative[0]) is None:
        return None
    path = PurePosixPath(relative[1])
    if path.is_absolute() or ".." in path.parts:
        return None
    return Path(os.path.abspath(roots[relative[0]])) / path


def _here(folder: Path, mount: Path) -> bool:
    """Whether the absolute `folder` lies on this machine on the filesystem mounted at `mount` (the folder itself may
    be gone: a job's own temporary folder is removed as the job ends; its nearest existing parent is asked)."""
    try:
        return folder.is_absolute() and mount_point(folder) == mount
    except OSError:
        return False


def _total_or(folder, default: int) -> int:
    """`total_bytes` of `folder`'s filesystem, or `default` where it cannot be asked."""
    try:
        return total_bytes(folder)
    except OSError:
        return default


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


__all__ = ["MAX_FULL_DISK", "free_bytes", "total_bytes", "mount_point", "same_filesystem", "full_folder",
           "folder_bytes", "size_text", "ROOM_MARGIN", "ROOM_RETRY_S", "ROOM_RETRY_MAX_S", "ROOM_SKEW_S", "ROOTS",
           "RoomWait", "missing_room", "room_missing", "note_doubt", "room_line", "room_said", "held_said",
           "holding_said", "names_said", "NAMED", "UNKNOWN_TIME", "when_text", "retry_after"]
