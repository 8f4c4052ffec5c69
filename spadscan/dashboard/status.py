"""What `/api/status` answers: the scans under the root, the scan in hand in detail, each scan's reconstructions and
the reconstruction queue (the worker's read-only status view, with each running job's progress from its log), what
the reconstruction side is doing (worker_state.py: the waits for room on a full disk included, the workers' and those
of the queued jobs that hold every claim, in the line the page shows), whether the dashboard's machine can draw
pictures off screen (`cannot_draw`: the 3D views need not, the browser draws them) and what each panel of a preview
shows. A live reconstruction whose status an earlier attempt of its job wrote is shown without its figures and
pictures (attempts.py).

Whether a daemon is running is asked of the caller's `daemon_running(root)`: the daemon's lock probe lives in the
daemon's package, which the dashboard does not import (the CLI command hands it over). Without it, scans are shown
as their scan.json says.

The daemon writes nothing else under the root that says what it does (its lock file holds only its pid). Where the
caller hands over `daemon_status(root)` (the CLI asks the daemon's control socket, as `spadscan ctl status` does),
the daemon's own status is shown (`daemon_status`: its state in its own words, the scan it holds, a scan it could not
take over and why) and the scans in hand as it says them (scans.py `as_the_daemon_says`); where it cannot be asked
(another user's daemon, another socket), `daemon_status_note` says why, and a daemon that paused but could not
record it in scan.json (a full disk) or that hangs is told from its scan's files alone, by the age of its last pose
(scans.py `stalled`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

from spadscan.protocol.errors import SpadscanError
from spadscan.worker.job_progress import progress_field, running_progress
from spadscan.worker.presence import present_workers, start_command
from spadscan.worker.queue import QUEUE_DIRNAME, Queue
from spadscan.worker.report.mesh_pictures import VIEWS
from spadscan.worker.report.offscreen import OffscreenUnavailable, check_offscreen
from spadscan.worker.status_detail import status_parts

from .attempts import claim_starts, earlier_attempt, last_claim_change
from .results import ResultIndex, serious_count
from .scans import (IN_HAND, INTERRUPTED, NOT_TAKEN_OVER, STALLED, ScanIndex, as_the_daemon_says, interrupted,
                    scan_detail, stalled)
from .worker_state import needs_freed, unfollowed, worker_state

PREVIEW = {"columns": [f"az {az:.0f}\u00b0 el {el:.0f}\u00b0" for az, el in VIEWS],
           "rows": ["reconstruction", "ground truth"]}
"""What each panel of a preview.png shows (worker/report/mesh_pictures.py `preview_png`: a column per angle, the
reconstruction's row above the ground truth's when there is one): the page labels them in its own, readable, type."""


DAEMON_KEYS = ("state", "scan", "progress", "reason", "last_error", "cannot_take_over", "also_interrupted",
               "poses_to_take_again", "poses_to_take_again_note", "pausing_at")
"""What the answer's `daemon_status` keeps of the daemon's own status (`spadscan ctl status`)."""
DAEMON_ASKED_S = 1.0
"""The daemon's status is asked at most once in this many seconds after its last answer came, however many pages
poll, and by one poll at a time (the others meanwhile show its last answer)."""


def cannot_draw() -> str | None:
    """Why this dashboard's machine cannot draw meshes off screen (no display, no EGL, no OSMesa: the product's own
    check, in one line with what to install), or None where it can. The browser draws the 3D views; the pictures (a
    preview) are drawn off screen by the worker, on its own machine: the page says a result's own reason where its
    report gives one (results.py `no_preview`), and this one, as this dashboard's machine's, only where it does not."""
    try:
        check_offscreen()
    except OffscreenUnavailable as exc:
        return str(exc)
    return None


def queue_status(queue_dir: Path, root: Path | None = None) -> dict:
    """The queue's jobs as `spadscan worker --status --json` lists them, a running job with its progress, and each
    job's `detail`: the last column of `spadscan worker --status` (a kept result, damaged queue files), made by the
    same function, and `warnings`, how many warnings a done job's report gives (the page prints them once, in the
    panel of the result in view: here a count leads there, as the terminal's "(3 warnings below)"). Its running
    jobs' progress is left out there: the page has a column for it (a live job's line from its scan's live status,
    under `root`, while it follows the scan)."""
    queue = Queue(queue_dir, create=False)
    running = running_progress(queue, root)  # a job with a budget is shown against it
    jobs = [{**asdict(row), **progress_field(row.state, row.id, running), **job_detail(row, root)}
            for row in queue.statuses()]
    return {"path": str(queue.path), "jobs": jobs, "counts": queue.counts()}


def queue_room_waits(queue_dir: Path, root: Path) -> list[tuple[str, dict]]:
    """(job id, its wait) for each queued job given back on a full disk whose room is still missing, as a worker's
    claim reads them (Queue.room_waits: no claim succeeds meanwhile; the folders found under this machine's queue and
    `root`); none where the queue cannot be read."""
    try:
        return list(Queue(queue_dir, create=False, root=root).room_waits())
    except OSError:
        return []


def job_detail(row, root: Path | None) -> dict:
    """{"detail": the row's last --status column without its warnings, "warnings": how many there are,
    "serious_warnings": how many of them doubt the shape itself (results.py `warning_level`)}."""
    detail, warnings, notes = status_parts(row, root=root)
    return {"detail": "; ".join([detail, *notes]), "warnings": len(warnings),
            "serious_warnings": serious_count(warnings)}


class Dashboard:
    """The state of one captures root (and its queue), read again at each poll; safe to call from several threads.

    `daemon_running(root)` says whether a daemon holds the root (asked once a poll): when none does, a scan still in
    hand is shown as interrupted, without a frame rate, and the answer's `daemon` is False (the page says so even
    while the rig is idle, when no scan shows it). None: scans are shown as their scan.json says, `daemon` None.
    Either way a running scan without news for too long is shown as stalled (scans.py `stalled`), by `clock`'s time
    (unix seconds: the file times' clock). Whether this machine can draw off screen (`cannot_draw`) is asked once:
    its libraries do not change while it runs."""

    def __init__(self, root, queue_dir=None, daemon_running: Callable[[Path], bool] | None = None,
                 clock: Callable[[], float] = time.time, daemon_status: Callable[[Path], dict] | None = None):
        self.root = Path(root)
        self.daemon_status = daemon_status
        self._asked: tuple[float, dict | None, str | None] | None = None
        """(`clock` when the daemon's last answer came, what it said, why it could not be asked), or None."""
        self._asking = threading.Lock()  # held by the poll that asks the daemon
        self.queue_dir = Path(queue_dir) if queue_dir else self.root / QUEUE_DIRNAME
        self.daemon_running = daemon_running
        self.clock = clock
        self.cannot_draw = cannot_draw()
        self.scans = ScanIndex(self.root)
        self.results = ResultIndex(self.root)
        self._lock = threading.Lock()
        self._detail: tuple[tuple, dict] | None = None

    def _scan_detail(self, row) -> dict:
        """The detail of the scan in hand, read again only when it has published a chunk or changed state (a stalled
        scan's reason says how long it has been quiet: it is the row's, new at each poll)."""
        key = (row.name, row.state, row.updated_utc, tuple(row.chunks[-1:]), row.error)
        if self._detail is None or self._detail[0] != key:
            self._detail = (key, scan_detail(self.root, row))
        return {**self._detail[1], "reason": row.reason, "quiet_s": row.quiet_s}

    def status(self) -> dict:
        # a daemon that starts or dies while the scans are read is seen at the next poll
        daemon = None if self.daemon_running is None else bool(self.daemon_running(self.root))
        orphaned = daemon is False
        now = self.clock()
        said, unsaid = self._daemon_said() if daemon else (None, None)
        with self._lock:
            rows = self.scans.rows()
            # in place: the order (scans in hand first) stays, and the scan is still the one in hand
            if orphaned:
                rows = [interrupted(r) if r.state in IN_HAND else r for r in rows]
            if said is not None:
                rows = [as_the_daemon_says(r, said) for r in rows]
            rows = [stalled(r, now) for r in rows]
            current = next((r for r in rows if r.state in IN_HAND + (INTERRUPTED, STALLED, NOT_TAKEN_OVER)),
                           None) or next(
                (r for r in rows if r.state != "error"), None)
            detail = self._scan_detail(current) if current is not None else None
            recons = {row.name: self.results.for_scan(row.name) for row in rows}
        try:
            queue = queue_status(self.queue_dir, self.root)
        except OSError as exc:
            queue = {"path": str(self.queue_dir), "jobs": [], "counts": {}, "error": str(exc)}
        # the folders read before the queue: each live status is judged against claims at least as new as itself
        starts = claim_starts(queue["jobs"])
        scans = [{**row.to_dict(), "recons": [earlier_attempt(r, starts) for r in recons[row.name]]} for row in rows]
        # time_unix: the server's clock, against which the page says how old each time it shows is (the browser's
        # clock may be another machine's)
        return {"root": str(self.root.resolve()), "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(now)),
                "time_unix": now, "root_missing": not self.root.is_dir(),
                "daemon": daemon, "daemon_config": next((r.config for r in rows if r.config), None),
                "daemon_status": said, "daemon_status_note": unsaid,
                "scans": scans, "current": detail, "queue": queue,
                "worker": self._worker(rows, queue, now), "preview": PREVIEW, "cannot_draw": self.cannot_draw}

    def _daemon_said(self) -> tuple[dict | None, str | None]:
        """(the running daemon's own status, DAEMON_KEYS of it; None where it cannot be asked), (why not, or None):
        asked of `daemon_status` once DAEMON_ASKED_S have passed since its last answer came (a daemon slow to answer
        is not asked again at once), by one poll at a time: a poll that finds another asking takes the last answer,
        and waits for the asking one only where there is none yet. Only a daemon that writes to this root counts."""
        if self.daemon_status is None:
            return None, None
        with self._lock:
            last = self._asked
            age = None if last is None else self.clock() - last[0]  # (the clock read after the answer's stamp)
        if last is not None and 0 <= age < DAEMON_ASKED_S:
            return last[1], last[2]
        if not self._asking.acquire(blocking=last is None):
            return last[1], last[2]
        try:
            with self._lock:
                if self._asked is not last:  # answered while this poll waited for the first answer
                    return self._asked[1], self._asked[2]
            said, unsaid = self._ask_daemon()
            with self._lock:
                self._asked = (self.clock(), said, unsaid)
        finally:
            self._asking.release()
        return said, unsaid

    def _ask_daemon(self) -> tuple[dict | None, str | None]:
        """`_daemon_said`'s answer, asked of `daemon_status` now."""
        try:
            reply = self.daemon_status(self.root)
            captures = (reply.get("daemon") or {}).get("captures")
            if captures is not None and Path(captures).resolve() != self.root.resolve():
                return None, (f"the daemon that answers on its socket writes to {captures}, not to this root: its "
                              f"state is told from the scans' files")
            return {k: reply[k] for k in DAEMON_KEYS if k in reply}, None
        except (SpadscanError, OSError) as exc:
            return None, f"the daemon's own state cannot be asked ({exc}): it is told from the scans' files"

    def _worker(self, rows, queue: dict, now: float) -> dict:
        """What the reconstruction side is doing (worker_state; "unknown" when the queue cannot be read), with the
        command that starts a worker, how many job processes the workers present run at once (`processes`), each
        worker's (`each`: its `name` as `workers` gives it and its `processes`), and the scans being recorded that no
        worker follows (`unfollowed`: a worker without --live leaves them)."""
        workers = [] if queue.get("error") else present_workers(self.queue_dir, now)
        held = queue_room_waits(self.queue_dir, self.root) if _queued(queue) else []
        start = start_command(self.root, self.queue_dir)
        state = {"state": "unknown"} if queue.get("error") else worker_state(
            rows, queue["jobs"], now, workers, self._freed(queue["jobs"]), held, start)
        each = [{"name": f"{w['host']} pid {w['pid']}", "processes": w["processes"]} for w in workers]
        return {**state, "start": start,
                "processes": sum(w["processes"] for w in workers), "each": each,
                "unfollowed": unfollowed(rows, {j["scan"] for j in queue["jobs"]}, now) if workers else []}

    def _freed(self, jobs: list[dict]) -> float | None:
        """When a claim last began or ended, where the worker's state depends on it (its attempt records are read
        then only: a queued job waiting long with no job running); None otherwise, or when the queue cannot say."""
        if not needs_freed(jobs):
            return None
        try:
            return last_claim_change(self.queue_dir, [j["id"] for j in jobs])
        except OSError:
            return None


def _queued(queue: dict) -> bool:
    """Whether the queue read (`queue_status`'s) has a job queued: only then can a queued job's wait hold it."""
    return not queue.get("error") and any(j["state"] == "queued" for j in queue["jobs"])
