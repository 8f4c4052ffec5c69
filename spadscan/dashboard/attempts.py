"""What the queue's attempt records tell the page: which attempt of a live job the live folder speaks for, and when a
worker last began or ended a job.

When a live job is taken over (its worker died, or gave it back) and claimed again, the new attempt's process takes
seconds to start before it clears the live folder and writes its first status (worker/live/job.py `begin`). Until
then the folder holds the earlier attempt's status, mesh and preview: beside a job that runs again, they would read
as the running attempt's. A live status written before its job's running claim began is an earlier attempt's; the
dashboard shows none of its figures or pictures (`earlier_attempt`).

A job queued behind another waits for a worker to be free, not for a worker that neglects it: with no job running,
it has been left untaken only since the last claim ended (`last_claim_change`), or since it was queued if later.
"""

from __future__ import annotations

import math
from pathlib import Path

from spadscan.protocol.iso_time import parse_utc
from spadscan.worker.queue import Queue

from .results import LIVE, LIVE_PICTURES


def claim_starts(jobs: list[dict]) -> dict[str, float]:
    """Each running job's claim start (unix seconds) by job id, where its attempt record gives it (`queue_status`)."""
    return {j["id"]: j["claimed_unix"] for j in jobs if j["state"] == "running" and j.get("claimed_unix") is not None}


def written_unix(entry: dict) -> float | None:
    """When a live entry's status was written, by its own `updated_utc` (the writer's clock, as the claim's start
    is); None when it does not say (every status the worker writes says it)."""
    then = parse_utc(entry["summary"].get("updated_utc"))
    return None if then is None else then.timestamp()


def earlier_attempt(entry: dict, starts: dict[str, float]) -> dict:
    """`entry` (a reconstruction of results.ResultIndex) as the page shows it: a live entry written before its job's
    running claim began keeps only its job's name, no figures, note or pictures, and says `earlier_attempt`; any other
    (one that does not say when it was written included) as it is."""
    job = entry["summary"].get("job") if entry["kind"] == LIVE else None
    start = starts.get(job) if isinstance(job, str) else None
    written = written_unix(entry) if start is not None else None
    if written is None or written >= start:
        return entry
    files = {name: url for name, url in entry["files"].items() if name not in LIVE_PICTURES}
    return {**entry, "summary": {"job": job}, "files": files, "earlier_attempt": True}


def last_claim_change(queue_dir: Path, job_ids: list[str]) -> float | None:
    """When a claim of one of `job_ids` last began or ended (unix seconds, the worker's clock), from their attempt
    records (a record is written when its claim begins and when it ends); None when no record says."""
    queue = Queue(queue_dir, create=False)
    return max((t for job in job_ids for record in queue.records(job) for t in claim_times(record)), default=None)


def claim_times(record: dict) -> list[float]:
    """The times an attempt record gives (unix seconds): its claim's start, and its end where it has ended (its
    `ended_utc`, to the second, and its start plus its `seconds`); a damaged field gives none."""
    start = record.get("started_unix")
    start = float(start) if _finite(start) else None
    times = [] if start is None else [start]
    if start is not None and _finite(record.get("seconds")):
        times.append(start + float(record["seconds"]))
    ended = parse_utc(record.get("ended_utc"))
    if ended is not None:
        times.append(ended.timestamp())
    return times


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
