"""Durable job queue (docs/job_queue.md): job files moved between state folders by atomic rename, with expiring leases.

Layout of a queue folder (by default `<captures root>/.queue/`):

```
ids/<job>.json                 registry: one entry per job ever queued, so a scan is queued once
queued/<job>.json              waiting to be claimed
running/<job>~<token>.json     claimed; <token> names the claim, the file's mtime is the holder's last heartbeat
done/<job>.json                finished, its result in place; the result folder is in its attempt records
failed/<job>.json              gave up; the one-line reason is in the job's last attempt record
attempts/<job>/<token>.json    one record per claim: holder (host, pid), times, outcome, error, result
tmp/                           files being written
```

Why several workers on one machine or on a shared filesystem run each job once:
- Job files are never rewritten, only renamed, and a rename of one source name succeeds for exactly one caller. So
  claiming (`queued/j` -> `running/j~T`), taking over an expired lease (`running/j~A` -> `running/j~B`) and finishing
  (`running/j~T` -> `done/j`) are each won by one process: the rename is the lock.
- A holder touches its `running/j~T` file (os.utime) every few seconds. A missing file means its lease expired and
  another worker took the job over: the holder drops its result.
- `retry_failed` with changed options (a failed job queued again with --device cpu, say) writes a new job file,
  registers it in ids/ and only then queues it: the queue never holds two files of one job.
- A job reaches done/ only once its result is in place (publishing.py): the queue never says done about a result
  that a crash can still lose.
- A lease expires when that file's mtime is older than the lease (clocks of machines sharing a filesystem must agree
  to well within the lease), or at once when the holder was a process on this machine that no longer exists
  (holder.py).
"""

from __future__ import annotations

import json
import math
import os
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from spadscan.protocol.errors import ConfigError

from .disk_room import missing_room, note_doubt
from .holder import Holder, holder_alive, holder_gone
from .jobs import CHANGEABLE, DEFAULT_QUEUE as QUEUE_DIRNAME, ID_RE as _ID_RE, Job
from .kill_points import kill_point


STATES = ("queued", "running", "done", "failed")
SEP = "~"
# Outcomes of one claim. Interrupted claims (the worker was asked to stop) and those that met a full disk (no fault of
# the job's: run again once there is room) do not count as attempts.
OUTCOMES = ("running", "done", "failed", "crashed", "lost", "interrupted", "disk_full")
UNCOUNTED = ("interrupted", "disk_full")


class Unrecorded(OSError):
    """A claim was settled, its job file moved to `state`/, but its attempt record could not be written (a full
    disk): `values` is what the record must still say (Queue.write_outcome). Until then the record says the claim
    is running and names no error."""

    def __init__(self, exc: OSError, state: str, values: dict):
        super().__init__(exc.errno, exc.strerror)
        self.state = state
        self.values = values


@dataclass
class Claim:
    """A job this process holds. `path` is its `running/` file; `attempt` counts this claim (1-based)."""

    job: Job
    token: str
    path: Path
    attempt: int
    started: float = field(default_factory=time.time)


@dataclass
class JobStatus:
    """One row of `spadscan worker --status`."""

    id: str
    scan: str
    preset: str
    state: str
    attempts: int
    error: str | None
    result: str | None
    holder: str | None
    heartbeat_age_s: float | None
    notes: list[str] = field(default_factory=list)
    """Damaged queue files of this job (unreadable job file, unreadable attempt records): what the row cannot say."""
    stale: str | None = None
    """For a running job whose holder seems gone: why (its process died, its lease expired, or it has missed
    heartbeats); None while its holder keeps renewing the lease."""
    shown_state: str = ""
    """`state` as --status shows it: 'stale' for a running job whose holder died or whose lease expired (the next
    worker takes it over), 'running?' for one whose holder has missed heartbeats while its lease still holds."""
    kept: bool = False
    """A done job that was not run: its results folder already held a result, which was kept."""
    claimed_unix: float | None = None
    """For a running job: when its running claim began (unix seconds, its attempt record's start), or None where the
    record does not say."""
    waiting_s: float | None = None
    """For a queued job: how long it has waited (its file's age: a job file is renamed into queued/ when it is queued
    or given back)."""
    owner: str = ""
    """A live job's owner token (`Job.owner`): its live status is its own only where the token matches."""


@dataclass(frozen=True)
class Reclaimed:
    """A running job taken over from a holder that is gone (`Queue.take_over_expired`)."""

    job_id: str
    state: str
    """Where it went: 'queued' (attempts left) or 'failed'."""
    why: str
    """Why its holder was given up on, as its lost claim's record and `--status` say it: `worker HOST pid N died
    mid-job` (its process is gone from this machine) or `worker HOST pid N stopped renewing its lease (...)`."""


def _utc() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


class Queue:
    """A job queue in one folder. Methods are safe to call from several processes at once."""

    def __init__(self, path, *, lease_s: float = 60.0, max_attempts: int = 3, create: bool = True,
                 root=None):
        """`create`: make the queue's folders; False for read-only uses (listing), which see a missing queue as
        empty. `root`: the captures root its jobs write under, where known: a wait for room noted relative to it
        (disk_room.RoomWait.relative) is found there (`room_wait`)."""
        if not (lease_s > 0):
            raise ConfigError(f"lease {lease_s} s must be > 0")
        if not (isinstance(max_attempts, int) and max_attempts >= 1):
            raise ConfigError(f"max attempts {max_attempts} must be an integer >= 1")
        self.path = Path(path)
        self.lease_s = float(lease_s)
        self.max_attempts = max_attempts
        self.root = None if root is None else Path(root)
        self._scans: dict[str, str] = {}  # registered_scan's answers: a job's scan never changes
        for sub in ("ids", "tmp", "attempts", *STATES) if create else ():
            (self.path / sub).mkdir(parents=True, exist_ok=True)

    @classmethod
    def for_root(cls, root, **kwargs) -> "Queue":
        return cls(Path(root) / QUEUE_DIRNAME, root=root, **kwargs)

    @property
    def roots(self) -> dict:
        """The folders a wait for room is noted relative to, as this machine names them (disk_room.ROOTS)."""
        return {"queue": self.path, "root": self.root}

    # ---- adding ----------------------------------------------------------------------------------------------
    def enqueue(self, job: Job) -> bool:
        """Queue a job unless its id was ever queued; True when it was added.

        The job file is written once into tmp/, hard-linked into ids/ (fails if the id exists: exactly one caller
        wins) and then renamed into queued/. A live job without an owner token gets one (`Job.owner`).
        """
        if not job.id or _ID_RE.search(job.id) or job.id.startswith("."):
            raise ConfigError(f"job id {job.id!r} must be a non-empty name of [A-Za-z0-9._-]")
        if self.known(job.id):
            return False
        if not job.created_utc:
            job = Job(**{**job.to_dict(), "created_utc": _utc()})
        if job.live and not job.owner:  # tells it from another queue's live job of the scan (Job.owner)
            job = Job(**{**job.to_dict(), "owner": secrets.token_hex(8)})
        tmp = self.path / "tmp" / f"{job.id}{SEP}{secrets.token_hex(6)}.json"
        _write_new(tmp, job.to_dict())
        try:
            os.link(tmp, self._id_path(job.id))
        except FileExistsError:
            tmp.unlink(missing_ok=True)
            return False
        os.rename(tmp, self.path / "queued" / f"{job.id}.json")
        return True

    def known(self, job_id: str) -> bool:
        return self._id_path(job_id).exists()

    def registered_scan(self, job_id: str) -> str | None:
        """The scan of the job registered as `job_id`: None when no job was ever queued under that id, "" when its
        registered file names none (damaged). A job's scan never changes (a retry changes only its options), so the
        answer is remembered: a watcher asks it of every scan on every pass, at the cost of a stat."""
        if not self.known(job_id):
            return None
        if job_id in self._scans:
            return self._scans[job_id]
        scan = _stored(self._id_path(job_id)).get("scan")
        scan = scan if isinstance(scan, str) else ""
        if scan:
            self._scans[job_id] = scan
        return scan

    def _id_path(self, job_id: str) -> Path:
        return self.path / "ids" / f"{job_id}.json"

    # ---- claiming --------------------------------------------------------------------------------------------
    def claim(self, holder: Holder | None = None, skipped: list | None = None) -> Claim | None:
        """Take the oldest queued live job, else the oldest queued job (first queued, first run: by its file's mtime,
        which a job gets when it is queued or given back), or None when there is none. A live job follows a scan
        that is being recorded: behind a backlog of finished scans its fit would start after the scan's end, which
        is what a live job is for. Race-free: the one rename that succeeds wins.

        None, too, while a job given back on a full disk waits for room (`room_wait`): that job would meet the full
        disk again, and so would any other, whose log and result go where that one's went. A claim whose attempt
        record does not fit (the queue's own disk full) puts the job back and raises the OSError.

        A queued job file this process may not take (another user's on a shared queue: EACCES) is passed over, its id
        and the OSError (which names the file) added to `skipped`, and the others are claimed: its error stopped every
        claim, poll after poll. One that cannot be read once taken (a folder in its place) fails as a damaged one
        does."""
        holder = holder or Holder.current()
        paths = list((self.path / "queued").glob("*.json"))
        if self.room_wait(paths) is not None:
            return None
        for src in _claim_order(paths):
            job_id = src.stem
            how, _ = self.live_claim(src, take=True)
            if how == "wait":
                continue  # another live job follows its scan: this one waits for the scan's end, holding no worker
            token = _new_token()
            dst = self.path / "running" / f"{job_id}{SEP}{token}.json"
            try:
                queued = src.stat()  # its place in the queue, should the claim put it back
                os.utime(src)  # the lease starts now: a rename keeps the old mtime
                os.rename(src, dst)
            except FileNotFoundError:
                continue  # another worker claimed it first
            except OSError as exc:
                if skipped is not None:
                    skipped.append((job_id, exc))
                continue
            try:
                job = Job.from_dict(json.loads(dst.read_text()), str(dst))
            except (ValueError, ConfigError, OSError) as exc:
                self._settle(dst, job_id, "failed")
                self._record(job_id, token, holder, outcome="failed", error=f"unreadable job file: {exc}")
                continue
            if how == "ordinary":  # its scan has ended and another live job holds its live folder
                job = Job(**{**job.to_dict(), "live": False})
            attempt = self.attempts(job_id) + 1
            try:
                self._record(job_id, token, holder, outcome="running", attempt=attempt)
            except OSError:  # a claim with no record would hold the job, unnamed, until its lease ran out
                _put_back(dst, src, queued, self.path / "tmp")
                raise
            return Claim(job, token, dst, attempt)
        return None

    def live_claim(self, path: Path, take: bool = False) -> tuple[str, str | None]:
        """How the queued job file `path` is claimed: ('claim', None) as it is; for a live job whose scan's live
        folder another live job holds (`worker.live.publish.live_holder`: another queue's job of its id on
        this root, another preset), ('wait', that job's id) while the scan is recorded, ('ordinary', that job's id)
        once the scan has ended.

        Claimed while its scan is recorded, such a job would hold a worker for the whole scan and publish nothing:
        it waits in the queue instead (`--status` says so), and once the scan has ended it is claimed as the
        ordinary job it then is, its budget counted from its process's start and the worker's overdue stop applied
        as to any ordinary job's (a live job's count from its own live status's 'final', which it never writes).
        `take`: mark the live folder the job's when it is free and its scan is recorded (a claim:
        `claim_live_folder`), so that of two queues' workers claiming the scan's live job at once one gets it and
        the other's waits. Without the captures root (`root`), or where the scan cannot be read (its process says
        why), ('claim', None)."""
        job = _job_file(path) if self.root is not None else None
        if job is None or not job.live:
            return "claim", None
        from spadscan.protocol.errors import SpadscanError

        from .jobs import scan_path, scan_state
        from .live.publish import claim_live_folder, live_holder

        state = scan_state(job, self.root)
        if state is None:
            return "claim", None
        try:
            holder = (claim_live_folder if state == "running" and take else live_holder)(scan_path(job, self.root), job)
        except (OSError, SpadscanError):
            return "claim", None
        if holder is None:
            return "claim", None
        return ("wait" if state == "running" else "ordinary"), holder

    def room_wait(self, paths=None, doubts: list | None = None) -> tuple[str, dict] | None:
        """(job id, its wait) for a queued job given back on a full disk whose room is still missing (the first of
        `room_waits`); None when no job waits."""
        return next(self.room_waits(paths, doubts), None)

    def room_waits(self, paths=None, doubts: list | None = None):
        """(job id, its wait) for each queued job given back on a full disk whose room is still missing: the last
        record of the job carries the wait (`release`'s `room`, disk_room.RoomWait.note) and its filesystem has not
        the room it needs nor has its retry time come (disk_room.missing_room: one statvfs, on the folder as found
        under this queue or its root, `roots`). The wait is given as read here: its folder this machine's, its
        retry time bounded. No claim succeeds until the last of them ends. `paths`: the queued job files, where the
        caller has listed them; `doubts`: a list that gets (job id, why) for each wait read otherwise than it says
        (disk_room.note_doubt)."""
        paths = (self.path / "queued").glob("*.json") if paths is None else paths
        for path in paths:
            room = self._room_of(path.stem)
            if room is None:
                continue
            doubt = note_doubt(room) if doubts is not None else None
            if doubt is not None:
                doubts.append((path.stem, doubt))
            wait = missing_room(room, roots=self.roots)
            if wait is not None:
                yield path.stem, wait.note()

    def _room_of(self, job_id: str) -> dict | None:
        """The wait the last record of a queued job carries (`release`'s `room`), or None. The record says
        'running' where its settling was cut short or could not be written yet (the job went back all the same)."""
        if not (self.path / "attempts" / job_id).is_dir():
            return None  # never claimed: the cheap answer for a queue of new jobs
        recs = self.records(job_id)
        last = recs[-1] if recs else {}
        room = last.get("room")
        return room if isinstance(room, dict) and last.get("outcome") in ("disk_full", "running") else None

    def heartbeat(self, claim: Claim) -> bool:
        """Renew the lease; False when it was lost (another worker took the job over)."""
        try:
            os.utime(claim.path)
            return True
        except FileNotFoundError:
            return False

    def restore_removed(self, claim: Claim, reason: str) -> bool:
        """A held job whose file left running/ with the job in no state folder (its file removed by hand: a worker
        that takes a job over renames the file, so the job stays somewhere) goes to failed/ from its registered file
        (ids/, a link to the same file), its claim's record saying `reason`: a queue never loses a job. False when
        the job is in a state folder (taken over) or cannot be put back (its ids/ entry gone too)."""
        job_id = claim.job.id
        # Looked for twice, in the order a job moves through the folders: a job moving while it is looked for shows
        # in one of the two looks.
        if self._in_some_state(job_id) or self._in_some_state(job_id):
            return False
        try:
            os.link(self._id_path(job_id), self.path / "failed" / f"{job_id}.json")
        except (FileNotFoundError, FileExistsError):
            return False
        try:
            self.write_outcome(claim, {"outcome": "failed", "error": _one_line(reason), "retried": False,
                                       "ended_utc": _utc(), "seconds": round(time.time() - claim.started, 3)})
        except OSError:
            pass  # the queue's disk is full: the job is in failed/ all the same, its record left as it was
        return True

    def _in_some_state(self, job_id: str) -> bool:
        """Whether a file of the job is in a state folder, or in tmp/ on its way to queued/ (`repair`)."""
        return ((self.path / "queued" / f"{job_id}.json").exists()
                or any((self.path / "running").glob(f"{job_id}{SEP}*.json"))
                or any((self.path / state / f"{job_id}.json").exists() for state in ("done", "failed"))
                or any((self.path / "tmp").glob(f"{job_id}{SEP}*.json")))

    # ---- finishing -------------------------------------------------------------------------------------------
    def finish(self, claim: Claim, result: str | None = None, *, kept: bool = False) -> bool:
        """Move a held job to done/; False (and nothing changes) when the lease was lost. Call it only once the
        job's result is in place (publishing.py). `kept`: the job was not run because `result` already held one
        (recorded, so that --status can say so)."""
        if not self._settle(claim.path, claim.job.id, "done"):
            return False
        kill_point("settled")
        self._update(claim, outcome="done", result=result, **({"kept": True} if kept else {}))
        return True

    def record_result(self, claim: Claim, result: str) -> None:
        """Note in a held job's attempt record the folder its result is being published to (before `finish`, so
        that a done job's record always names its result, even when its worker died between the two)."""
        self._patch_record(claim.job.id, claim.token, result=result)

    def note_job_process(self, claim: Claim, pid: int) -> None:
        """Record the process that runs a held job, so that another worker can tell when it has exited (an orphan
        may write into its scratch folder for a moment after its worker died)."""
        self._patch_record(claim.job.id, claim.token, job_process=Holder.of_pid(pid).to_dict())

    def job_process_gone(self, job_id: str, token: str) -> bool:
        """False while the job process of claim `token` is seen running on this machine; True otherwise (it has
        exited, none was recorded, or it ran elsewhere: a claim from another machine is taken over only once its
        lease has expired, long after its orphaned job process noticed that its worker was gone)."""
        proc = (self._read_record(job_id, token) or {}).get("job_process")
        return not (isinstance(proc, dict) and holder_alive(proc))

    def adopt(self, job_id: str, path: Path, dead_token: str, *, why: str,
              holder: Holder | None = None) -> Claim | None:
        """Take a job over to settle it with the finished result that claim `dead_token`, whose holder died, left
        behind, without running it again. `path` is the job's file wherever it is now: running/ under a dead claim
        (that one, or one that adopted it and died too), or queued/ or failed/ (a worker took the dead claim over
        meanwhile). Exactly one caller wins (the rename); None for the others. The new claim is not an attempt:
        it is marked adopted, and the dead claims' records say why they ended (`why`)."""
        holder = holder or Holder.current()
        new = _new_token()
        dst = self.path / "running" / f"{job_id}{SEP}{new}.json"
        self._record(job_id, new, holder, outcome="running", adopted=dead_token)  # before the rename: never unnamed
        try:
            os.utime(path)  # the lease starts now: a rename keeps the old mtime
            os.rename(path, dst)
        except FileNotFoundError:
            (self.path / "attempts" / job_id / f"{new}.json").unlink(missing_ok=True)
            return None
        kill_point("adopted")
        held = path.stem.rpartition(SEP)[2] if path.parent.name == "running" else None
        for token in dict.fromkeys(t for t in (dead_token, held) if t):
            self._patch_record(job_id, token, outcome="lost", error=_one_line(why), ended_utc=_utc(), retried=False)
        try:
            job = Job.from_dict(json.loads(dst.read_text()), str(dst))
        except (OSError, ValueError, ConfigError):
            job = Job(id=job_id, scan="?")
        return Claim(job, new, dst, self.attempts(job_id))

    def note_adopted(self, claim: Claim, token: str) -> None:
        """Mark held claim `claim` as one that publishes the finished result claim `token` left (`adopted`: no
        attempt of its own, see `attempts`)."""
        self._patch_record(claim.job.id, claim.token, adopted=token)

    def record_done(self, job_id: str, result: str) -> bool:
        """A done job whose last attempt record does not say so with its result (its worker died between moving the
        job file to done/ and updating the record, or before it recorded where it published the result): complete
        that record. True when it was changed."""
        recs = self.records(job_id)
        if not recs or not recs[-1].get("token") or (recs[-1].get("outcome") == "done" and recs[-1].get("result")):
            return False
        self._patch_record(job_id, str(recs[-1]["token"]), outcome="done", result=result,
                           ended_utc=recs[-1].get("ended_utc") or _utc())
        return True

    def last_error(self, job_id: str) -> str | None:
        """The error of the job's last counted attempt (as --status shows it), or None."""
        errors = [str(r["error"]) for r in self.records(job_id) if _counted(r) and r.get("error")]
        return errors[-1] if errors else None

    def job_in(self, state: str, job_id: str) -> Job | None:
        """The job file `job_id` in `state`/ (queued, done or failed), or None when it is not there or unreadable."""
        path = self.path / state / f"{job_id}.json"
        try:
            return Job.from_dict(json.loads(path.read_text()), str(path))
        except (OSError, ValueError, ConfigError):
            return None

    def record(self, job_id: str, token: str) -> dict | None:
        """The attempt record of claim `token`, or None when it is missing or unreadable."""
        return self._read_record(job_id, token)

    def fail(self, claim: Claim, reason: str, *, retry: bool, outcome: str = "failed") -> str | None:
        """A claim ended in error. With `retry` and attempts left the job goes back to queued/, else to failed/.

        Returns the new state, or None when the lease had been lost (nothing changes). Raises Unrecorded when the job
        file moved but its attempt record could not be written (a full disk: a rename needs no free space, a record
        does); `write_outcome` writes it later.
        """
        retry = retry and claim.attempt < self.max_attempts
        state = "queued" if retry else "failed"
        if not retry and claim.attempt > 1 and claim.attempt >= self.max_attempts:
            reason = f"{reason} (attempt {claim.attempt} of {self.max_attempts}; giving up)"
        values = {"outcome": outcome, "error": _one_line(reason), "retried": retry, "ended_utc": _utc(),
                  "seconds": round(time.time() - claim.started, 3)}
        if not self._settle(claim.path, claim.job.id, state):
            return None
        try:
            self.write_outcome(claim, values)
        except OSError as exc:
            raise Unrecorded(exc, state, values) from exc
        return state

    def crash(self, claim: Claim, reason: str) -> str | None:
        """The job's process died or raised unexpectedly: retried while attempts are left."""
        return self.fail(claim, reason, retry=True, outcome="crashed")

    def write_outcome(self, claim: Claim, values: dict) -> None:
        """Write how a settled claim ended into its attempt record (what Unrecorded.values says, once it fits)."""
        self._patch_record(claim.job.id, claim.token, **values)

    def release(self, claim: Claim, reason: str = "worker stopped", *, outcome: str = "interrupted",
                room: dict | None = None) -> bool:
        """Give a held job back to queued/ without counting the attempt: the worker was asked to stop
        ('interrupted'), or the job met a full disk ('disk_full'). False (and nothing changes) when the lease was
        lost. Raises Unrecorded when the job went back but its attempt record could not be written.

        `room`: the wait for room a full disk began (disk_room.RoomWait.note), kept in the record, written there
        before the job goes back too: no worker claims a job, this one or another, while it is still missing
        (`claim`)."""
        if room is not None:
            try:
                self._patch_record(claim.job.id, claim.token, room=room)
            except OSError:
                pass  # the queue's disk is full: the record after the rename will not fit either (Unrecorded)
        if not self._settle(claim.path, claim.job.id, "queued"):
            return False
        values = {"outcome": outcome, "error": _one_line(reason), "ended_utc": _utc(),
                  "seconds": round(time.time() - claim.started, 3), **({"room": room} if room is not None else {})}
        try:
            self.write_outcome(claim, values)
        except OSError as exc:
            raise Unrecorded(exc, "queued", values) from exc
        return True

    def _settle(self, src: Path, job_id: str, state: str) -> bool:
        try:
            os.rename(src, self.path / state / f"{job_id}.json")
            return True
        except FileNotFoundError:
            return False

    # ---- expired leases --------------------------------------------------------------------------------------
    def reclaim_expired(self, holder: Holder | None = None, now: float | None = None,
                        before_requeue: Callable[[Job, str], None] | None = None) -> list[tuple[str, str]]:
        """`take_over_expired`, as [(job id, new state)]."""
        return [(r.job_id, r.state) for r in self.take_over_expired(holder, now, before_requeue)]

    def take_over_expired(self, holder: Holder | None = None, now: float | None = None,
                          before_requeue: Callable[[Job, str], None] | None = None) -> list[Reclaimed]:
        """Take over every running job whose holder stopped; retry it or fail it. Returns what became of each, and
        why its holder was given up on (`Reclaimed`).

        `before_requeue(job, why)` is called for each job about to be retried while this process still holds it:
        once back in queued/, another worker may claim it at once, and its attempt's first word must not be covered
        by a note written after (a live job's status saying it is queued again, as on every path that gives a job
        back)."""
        holder = holder or Holder.current()
        out = []
        for path in sorted((self.path / "running").glob(f"*{SEP}*.json")):
            job_id, _, old_token = path.stem.rpartition(SEP)
            why = self._expired(path, job_id, old_token, now)
            if why is None:
                continue
            token = _new_token()
            mine = path.with_name(f"{job_id}{SEP}{token}.json")
            try:
                # A fresh mtime first: under its new name, with no record, the file must not look expired to another
                # worker's reclaim before this one settles it (that one would record a claim that never ran).
                os.utime(path)
                os.rename(path, mine)  # exactly one reclaimer wins
            except FileNotFoundError:
                continue
            attempts = self.attempts(job_id)
            retry = attempts < self.max_attempts
            reason = why if retry else f"{why} (attempt {attempts} of {self.max_attempts}; giving up)"
            self._patch_record(job_id, old_token, outcome="lost", error=reason, ended_utc=_utc(), retried=retry)
            held = _job_file(mine) if retry and before_requeue is not None else None
            if held is not None:
                before_requeue(held, reason)
            state = "queued" if retry else "failed"
            if self._settle(mine, job_id, state):
                out.append(Reclaimed(job_id, state, why))
        return out

    def _expired(self, path: Path, job_id: str, token: str, now: float | None) -> str | None:
        """Why the lease on `path` has expired, or None while it holds."""
        try:
            mtime = path.stat().st_mtime
        except FileNotFoundError:
            return None
        rec = self._read_record(job_id, token) or {}
        lease = _number(rec.get("lease_s")) or self.lease_s
        who = f"worker {rec.get('host', '?')} pid {rec.get('pid', '?')}"
        if rec.get("holder") and holder_gone(rec["holder"]):
            return f"{who} died mid-job"
        age = (time.time() if now is None else now) - mtime
        if age > lease:
            return f"{who} stopped renewing its lease ({age:.0f} s > {lease:.0f} s)"
        return None

    def claim_is_dead(self, job_id: str, token: str) -> bool:
        """True when claim `token` of a job can never publish a result: its lease was taken over ('lost') or its
        holder is a process on this machine that no longer exists. False for live claims, for settled claims whose
        holder may still be moving its result into place, and for unknown tokens."""
        rec = self._read_record(job_id, token)
        if not isinstance(rec, dict):
            return False
        if rec.get("outcome") == "lost":
            return True  # finish() can no longer succeed for it, so its holder will never publish
        holder = rec.get("holder")
        return isinstance(holder, dict) and holder_gone(holder)

    # ---- attempt records -------------------------------------------------------------------------------------
    def attempts(self, job_id: str) -> int:
        """Claims of this job that counted as attempts (interrupted and adopted ones do not)."""
        return sum(1 for r in self.records(job_id) if _counted(r))

    def records(self, job_id: str) -> list[dict]:
        """Attempt records of one job, oldest first; unreadable ones are left out (see `read_records`)."""
        return self.read_records(job_id)[0]

    def read_records(self, job_id: str) -> tuple[list[dict], list[Path]]:
        """(attempt records of one job, oldest first; the record files that are not readable JSON objects).

        Records are replaced whole by rename, so an unreadable one is damage (a torn file after a power cut, a file
        emptied by hand), not one being written: it is set aside, never fatal."""
        folder = self.path / "attempts" / job_id
        recs, bad = [], []
        for p in sorted(folder.glob("*.json")) if folder.is_dir() else ():
            try:
                rec = json.loads(p.read_text())
            except (OSError, ValueError):
                rec = None
            if isinstance(rec, dict):
                recs.append(rec)
            elif p.exists():  # a record replaced while being read is gone, not bad
                bad.append(p)
        return sorted(recs, key=lambda r: (_number(r.get("started_unix")), str(r.get("token", "")))), bad

    def _record(self, job_id: str, token: str, holder: Holder, **values) -> None:
        rec = {"token": token, **holder.describe(), "holder": holder.to_dict(), "lease_s": self.lease_s,
               "started_utc": _utc(), "started_unix": time.time(), "ended_utc": None, "error": None,
               "result": None, **values}
        self._write_record(job_id, token, rec)

    def _update(self, claim: Claim, **values) -> None:
        values.setdefault("ended_utc", _utc())
        values.setdefault("seconds", round(time.time() - claim.started, 3))
        self._patch_record(claim.job.id, claim.token, **values)

    def _patch_record(self, job_id: str, token: str, **values) -> None:
        rec = self._read_record(job_id, token) or {"token": token, "started_unix": time.time()}
        rec.update(values)
        self._write_record(job_id, token, rec)

    def _read_record(self, job_id: str, token: str) -> dict | None:
        try:
            rec = json.loads((self.path / "attempts" / job_id / f"{token}.json").read_text())
        except (OSError, ValueError):
            return None
        return rec if isinstance(rec, dict) else None

    def _write_record(self, job_id: str, token: str, rec: dict) -> None:
        folder = self.path / "attempts" / job_id
        folder.mkdir(parents=True, exist_ok=True)
        tmp = self.path / "tmp" / f"rec-{job_id}{SEP}{token}-{secrets.token_hex(4)}.json"
        _write_new(tmp, rec)
        os.replace(tmp, folder / f"{token}.json")

    # ---- listing and maintenance -----------------------------------------------------------------------------
    def queued_jobs(self) -> list[Job]:
        """The jobs waiting in queued/, sorted by id; unreadable job files are left out (their claim fails them)."""
        jobs = []
        for p in sorted((self.path / "queued").glob("*.json")):
            try:
                jobs.append(Job.from_dict(json.loads(p.read_text()), str(p)))
            except (OSError, ValueError, ConfigError):
                continue
        return jobs

    def job_paths(self) -> dict[str, tuple[str, Path]]:
        """Every job file by id: (state, path). A job moving between listings may appear in either state."""
        found: dict[str, tuple[str, Path]] = {}
        for state in STATES:
            for p in (self.path / state).glob("*.json"):
                job_id = p.stem.rpartition(SEP)[0] if state == "running" else p.stem
                found[job_id] = (state, p)
        return found

    def statuses(self, states: tuple[str, ...] = STATES) -> list[JobStatus]:
        """One row per job in `states` (all by default), sorted by id. Damaged files (unreadable job file or attempt
        records) are named in the row's `notes`; the row says what the readable ones do. Only the rows asked for read
        their files: a queue's history of done and failed jobs grows without bound."""
        now = time.time()
        return [self._status(job_id, state, path, now) for job_id, (state, path) in sorted(self.job_paths().items())
                if state in states]

    def _status(self, job_id: str, state: str, path: Path, now: float) -> JobStatus:
        notes = []
        try:
            job = Job.from_dict(json.loads(path.read_text()), str(path))
        except (OSError, ValueError, ConfigError):
            job = Job(id=job_id, scan="?", preset="?")
            if path.exists():  # not just moved on to another state
                notes.append(f"unreadable job file {path}")
        recs, bad = self.read_records(job_id)
        notes += [f"unreadable attempt record {p}" for p in bad]
        if state in ("queued", "failed") and recs and recs[-1].get("outcome") == "running":
            # Moved on, its record not: a full disk kept out how the claim ended (the worker's log line says it).
            notes.append("its last attempt record was not written (a full disk?): the worker's log says how it ended")
        counted = [r for r in recs if _counted(r)]
        errors = [str(r["error"]) for r in counted if r.get("error")]
        if state == "queued" and recs and recs[-1].get("outcome") == "disk_full" and recs[-1].get("error"):
            errors.append(str(recs[-1]["error"]))  # why it waits (the disk to make room on), though not an attempt
        # A done job's result: its done record's; else the one its last claim recorded before settling (its worker
        # died between moving the job to done/ and updating the record).
        results = ([str(r["result"]) for r in recs if r.get("outcome") == "done" and r.get("result")]
                   or ([str(r["result"]) for r in recs if r.get("result")] if state == "done" else []))
        holder = age = stale = claimed = waiting = None
        shown = state
        if state == "running":
            token = path.stem.rpartition(SEP)[2]
            rec = next((r for r in recs if r.get("token") == token), {})
            holder = f"{rec.get('host', '?')}:{rec.get('pid', '?')}"
            claimed = _finite(rec.get("started_unix"))  # a damaged record's start says nothing
            age = file_age(path, now)
            shown, stale = self._stale(path, job_id, token, age, now) or (state, None)
        elif state == "queued":
            waiting = file_age(path, now)
            how, other = self.live_claim(path)
            if how == "wait":
                whose = "another queue's live job of this id" if other == job_id else f"live job {other}"
                notes.append(f"waits for scan {job.scan} to end, holding no worker: {whose} follows it live; then "
                             f"it reconstructs the scan as an ordinary job (its budget counted from its start)")
        done = [r for r in recs if r.get("outcome") == "done"]
        return JobStatus(job_id, str(job.scan), str(job.preset), state, len(counted),
                         errors[-1] if errors and state != "done" else None, results[-1] if results else None,
                         holder, age, notes, stale, shown, bool(done and done[-1].get("kept")), claimed, waiting,
                         job.owner)

    def _stale(self, path: Path, job_id: str, token: str, age: float | None,
               now: float) -> tuple[str, str] | None:
        """('stale' or 'running?', why) for a running job whose holder seems gone; None while it renews its lease.

        Holders renew every quarter lease (pool.py), so one silent for over half a lease has missed two renewals:
        probably dead, though its lease still holds and no worker will take the job over before it expires."""
        expired = self._expired(path, job_id, token, now)
        if expired is not None:
            return "stale", f"{expired}; the next worker to look at the queue takes it over"
        lease = _number((self._read_record(job_id, token) or {}).get("lease_s")) or self.lease_s
        if age is not None and age > lease / 2:
            return "running?", f"worker silent for {age:.0f} s (its lease of {lease:.0f} s has not expired yet)"
        return None

    def queued_ids(self) -> set[str]:
        """The ids of the jobs in queued/."""
        return {p.stem for p in (self.path / "queued").glob("*.json")}

    def counts(self) -> dict[str, int]:
        """Number of job files in each state."""
        return {s: sum(1 for _ in (self.path / s).glob("*.json")) for s in STATES}

    def retry_failed(self, job_id: str | None = None, *, changes: dict | None = None,
                     preset: str | None = None) -> list[str]:
        """Put failed jobs (one, or all; with `preset`, only those of that preset) back in the queue with a fresh
        attempt count. `changes`: job options (jobs.CHANGEABLE: budget_s, steps, device, seed) they are queued
        again with; the options not named keep the values the job was queued with. Returns the ids moved."""
        return self.requeue("failed", job_id, changes=changes, preset=preset)

    def requeue(self, state: str, job_id: str | None = None, *, changes: dict | None = None,
                preset: str | None = None) -> list[str]:
        """`retry_failed` for the jobs in `state` ('failed', or 'done' to run finished jobs again: their results
        are the caller's to move aside first, since a worker keeps a result it finds)."""
        if state not in ("failed", "done"):
            raise ConfigError(f"only failed or done jobs can be queued again, not {state} ones")
        bad = sorted(set(changes or {}) - set(CHANGEABLE))
        if bad:
            raise ConfigError(f"cannot change {', '.join(bad)} of a queued job (only {', '.join(CHANGEABLE)})")
        moved = []
        for p in sorted((self.path / state).glob("*.json")):
            if job_id is not None and p.stem != job_id:
                continue
            if preset is not None and _stored(p).get("preset") != preset:
                continue
            folder = self.path / "attempts" / p.stem
            if folder.is_dir():
                os.rename(folder, folder.with_name(f".{p.stem}{SEP}retired{SEP}{_new_token()}"))
            if self._requeue_changed(p, changes) if changes else _rename(p, self.path / "queued" / p.name):
                moved.append(p.stem)
        return moved

    def _requeue_changed(self, path: Path, changes: dict) -> bool:
        """Queue the failed (or done) job file `path` again as a new job file with `changes` applied; False when
        another process moved it first.

        Job files are never rewritten, so the changed job is a new file, and it becomes the job's registered one
        (ids/) before it is queued: a crash part-way leaves in tmp/ exactly one registered file, which `repair`
        queues (with the old options when the crash came before the new file was registered)."""
        job_id = path.stem
        held = self.path / "tmp" / f"{job_id}{SEP}{_new_token()}.json"
        try:
            os.utime(path)  # `repair` leaves a registered file in tmp/ alone for a minute after this
        except FileNotFoundError:
            return False
        if not _rename(path, held):  # exactly one caller wins
            return False
        data = _stored(held)
        if not {"id", "scan"} <= set(data):
            return _rename(held, self.path / "queued" / path.name)  # unreadable: its job fails again saying why
        fresh = self.path / "tmp" / f"{job_id}{SEP}{_new_token()}.json"
        _write_new(fresh, {**data, **changes})
        registered = self.path / "tmp" / f"id-{job_id}-{_new_token()}.json"  # no SEP: not a name `repair` reads
        os.link(fresh, registered)
        os.replace(registered, self._id_path(job_id))
        held.unlink(missing_ok=True)
        return _rename(fresh, self.path / "queued" / path.name)

    def repair(self, min_age_s: float = 60.0) -> list[str]:
        """Queue jobs whose enqueue was cut short between registering and queuing (a crash); returns their ids."""
        fixed = []
        now = time.time()
        for tmp in (self.path / "tmp").glob(f"*{SEP}*.json"):
            job_id = tmp.stem.rpartition(SEP)[0]
            try:
                st = tmp.stat()
                reg = self._id_path(job_id).stat()
            except FileNotFoundError:
                continue
            if st.st_ino != reg.st_ino or now - st.st_mtime < min_age_s:
                continue  # not this job's registered file, or its enqueue may still be in progress
            try:
                os.rename(tmp, self.path / "queued" / f"{job_id}.json")
                fixed.append(job_id)
            except FileNotFoundError:
                continue
        return fixed


def _counted(rec: dict) -> bool:
    """Whether an attempt record counts as an attempt: interrupted claims (the worker was asked to stop), those that
    met a full disk, and adopted ones (a finished result published for a dead worker) do not."""
    return rec.get("outcome") not in UNCOUNTED and not rec.get("adopted")


def _rename(src: Path, dst: Path) -> bool:
    """Rename `src` to `dst`; False when `src` is gone (another process moved it first)."""
    try:
        os.rename(src, dst)
        return True
    except FileNotFoundError:
        return False


def _put_back(claimed: Path, queued: Path, was: os.stat_result, tmp: Path) -> None:
    """Rename the job file a claim took (`claimed`) back to `queued`, with the times it had there (`was`): its place
    in the queue (the oldest first) is its file's mtime, which the claim had set to now.

    The times are restored under a private name in the queue's `tmp` folder, before the file is queued: restored in
    queued/, they could land on another worker's claim of it made in between (its utime, then our old times, then
    its rename), whose fresh lease would then look an hour old and be taken over while its job runs. The private
    name is one `repair` reads: a crash in between leaves the job to be queued again, not lost."""
    private = tmp / f"{queued.stem}{SEP}{_new_token()}.json"
    if not _rename(claimed, private):
        return
    try:
        os.utime(private, ns=(was.st_atime_ns, was.st_mtime_ns))
    except OSError:  # `repair` queued it meanwhile: its place is whatever that rename kept
        pass
    _rename(private, queued)


def _job_file(path: Path) -> Job | None:
    """The job in job file `path`, or None when it cannot be read (its next claim fails it, saying why)."""
    try:
        return Job.from_dict(json.loads(path.read_text()), str(path))
    except (OSError, ValueError, ConfigError):
        return None


def _stored(path: Path) -> dict:
    """A job file's contents, or {} when it cannot be read as a JSON object."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _finite(value) -> float | None:
    """A record's finite number, or None where a damaged record holds something else."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    return float(value) if ok else None


def file_age(path: Path, now: float) -> float | None:
    """Seconds since `path` was last modified (0 at least), or None when it has moved on meanwhile."""
    try:
        return max(0.0, now - path.stat().st_mtime)
    except FileNotFoundError:
        return None


def _number(value) -> float:
    """A record's number, or 0.0 where a damaged record holds something else."""
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else 0.0


def _claim_order(paths) -> list[Path]:
    """Queued job files `paths`, live jobs first, each kind by its files' mtime, then name (a file gone meanwhile
    goes last: its claim will fail; one that cannot be read counts as not live: its claim fails it)."""
    def key(path: Path) -> tuple[bool, float, str]:
        try:
            return not _is_live(path), path.stat().st_mtime, path.name
        except FileNotFoundError:
            return True, math.inf, path.name
    return sorted(paths, key=key)


def _is_live(path: Path) -> bool:
    """Whether the queued job file `path` holds a live job (FileNotFoundError when it has gone)."""
    try:
        return json.loads(path.read_text()).get("live") is True
    except FileNotFoundError:
        raise
    except (OSError, ValueError, AttributeError):
        return False


def _new_token() -> str:
    return secrets.token_hex(8)


def _one_line(text: str, limit: int = 500) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def _write_new(path: Path, data: dict) -> None:
    """Write a JSON file durably (fsync) before it is linked or renamed into place."""
    with open(path, "w") as f:
        json.dump(data, f, indent=1)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
