"""What `/api/status` answers: the scans under the root, the scan in hand in detail, each scan's reconstructions and
the reconstruction queue (the worker's read-only status view, with each running job's progress from its log).

Whether a daemon is running is asked of the caller's `daemon_running(root)`: the daemon's lock probe lives in the
daemon's package, which the dashboard does not import (the CLI command hands it over). Without it, scans are shown
as their scan.json says.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

from spadscan.worker.job_progress import claim_log, progress_field, running_progress
from spadscan.worker.status_detail import status_detail

from .results import ResultIndex
from .scans import IN_HAND, INTERRUPTED, ScanIndex, interrupted, scan_detail


FINAL_START_SAID = {"the final reconstruction continues from the live fit": "live",
                    "the final reconstruction starts from the carved hull": "hull"}
"""What a live job's log says as its final run begins (worker/live/job.py), and the start each phrase names."""


class FinalStarts:
    """Where each running live job's final run started ('live' or 'hull'): its log says it once, as that run begins
    (the live status does not). A log is read on from where the last poll stopped, and no more once it has said."""

    def __init__(self):
        self._logs: dict[str, tuple[int, str | None]] = {}
        """Log path -> (bytes read, up to a line's end; the start it names, None while it has not said)."""

    def of(self, log: Path) -> str | None:
        offset, found = self._logs.get(str(log), (0, None))
        if found is None:
            try:
                with open(log, "rb") as f:
                    f.seek(offset)
                    chunk = f.read()
            except OSError:
                return None
            end = max(chunk.rfind(b"\n"), chunk.rfind(b"\r")) + 1  # a line still being written is read again
            text = chunk[:end].decode("utf-8", "replace")
            found = next((start for said, start in FINAL_START_SAID.items() if said in text), None)
            self._logs[str(log)] = (offset + end, found)
        return found

    def keep_only(self, logs) -> None:
        """Forget the logs of the jobs no longer running."""
        for name in set(self._logs) - {str(log) for log in logs}:
            del self._logs[name]


def queue_status(queue_dir: Path, root: Path | None = None, final_starts: FinalStarts | None = None) -> dict:
    """The queue's jobs as `spadscan worker --status --json` lists them, a running job with its progress, and each
    job's `detail`: the last column of `spadscan worker --status` (a kept result, warnings, damaged queue files),
    made by the same function. Its running jobs' progress is left out there: the page has a column for it (a live
    job's line from its scan's live status, under `root`, while it follows the scan). A running job whose log says
    where its final run started has `final_start` ('live' or 'hull'; `final_starts` remembers the logs read)."""
    from spadscan.worker.queue import Queue

    queue = Queue(queue_dir, create=False)
    running = running_progress(queue, root)  # a job with a budget is shown against it
    logs = {job_id: claim_log(queue.path, path) for job_id, (state, path) in queue.job_paths().items()
            if state == "running"}
    final_starts = final_starts or FinalStarts()
    final_starts.keep_only(logs.values())
    jobs = [{**asdict(row), **progress_field(row.state, row.id, running), "detail": status_detail(row, root=root)}
            for row in queue.statuses()]
    for job in jobs:
        start = final_starts.of(logs[job["id"]]) if job["state"] == "running" and job["id"] in logs else None
        if start is not None:
            job["final_start"] = start
    return {"path": str(queue.path), "jobs": jobs, "counts": queue.counts()}


class Dashboard:
    """The state of one captures root (and its queue), read again at each poll; safe to call from several threads.

    `daemon_running(root)` says whether a daemon holds the root (asked once a poll): when none does, a scan still in
    hand is shown as interrupted, without a frame rate. None: scans are shown as their scan.json says."""

    def __init__(self, root, queue_dir=None, daemon_running: Callable[[Path], bool] | None = None):
        self.root = Path(root)
        self.queue_dir = Path(queue_dir) if queue_dir else self.root / ".queue"
        self.daemon_running = daemon_running
        self.scans = ScanIndex(self.root)
        self.results = ResultIndex(self.root)
        self._lock = threading.Lock()
        self._detail: tuple[tuple, dict] | None = None
        self._final_starts = FinalStarts()

    def _scan_detail(self, row) -> dict:
        """The detail of the scan in hand, read again only when it has published a chunk or changed state."""
        key = (row.name, row.state, row.updated_utc, tuple(row.chunks[-1:]), row.error)
        if self._detail is None or self._detail[0] != key:
            self._detail = (key, scan_detail(self.root, row))
        return self._detail[1]

    def status(self) -> dict:
        # a daemon that starts or dies while the scans are read is seen at the next poll
        orphaned = self.daemon_running is not None and not self.daemon_running(self.root)
        with self._lock:
            rows = self.scans.rows()
            if orphaned:  # in place: the order (scans in hand first) stays, and the scan is still the one in hand
                rows = [interrupted(r) if r.state in IN_HAND else r for r in rows]
            scans = []
            for row in rows:
                entry = row.to_dict()
                entry["recons"] = self.results.for_scan(row.name)
                scans.append(entry)
            current = next((r for r in rows if r.state in IN_HAND + (INTERRUPTED,)), None) or next(
                (r for r in rows if r.state != "error"), None)
            detail = self._scan_detail(current) if current is not None else None
        try:
            with self._lock:  # the logs read so far are shared between the server's threads
                queue = queue_status(self.queue_dir, self.root, self._final_starts)
        except OSError as exc:
            queue = {"path": str(self.queue_dir), "jobs": [], "counts": {}, "error": str(exc)}
        return {"root": str(self.root.resolve()), "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                "scans": scans, "current": detail, "queue": queue}
