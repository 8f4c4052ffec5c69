"""Which attempt of a live job the live folder speaks for.

When a live job is taken over (its worker died, or gave it back) and claimed again, the new attempt's process takes
seconds to start before it clears the live folder and writes its first status (worker/live/job.py `begin`). Until
then the folder holds the earlier attempt's status, mesh and preview: beside a job that runs again, they would read
as the running attempt's. A live status written before its job's running claim began is an earlier attempt's; the
dashboard shows none of its figures or pictures (`earlier_attempt`).
"""

from __future__ import annotations

import datetime as _dt

from .results import LIVE, LIVE_PICTURES


def claim_starts(jobs: list[dict]) -> dict[str, float]:
    """Each running job's claim start (unix seconds) by job id, where its attempt record gives it (`queue_status`)."""
    return {j["id"]: j["claimed_unix"] for j in jobs if j["state"] == "running" and j.get("claimed_unix") is not None}


def written_unix(entry: dict) -> float | None:
    """When a live entry's status was written, by its own `updated_utc` (the writer's clock, as the claim's start
    is); None when it does not say (every status the worker writes says it)."""
    try:
        then = _dt.datetime.fromisoformat(str(entry["summary"].get("updated_utc")))
    except ValueError:
        return None
    return (then if then.tzinfo else then.replace(tzinfo=_dt.timezone.utc)).timestamp()


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
