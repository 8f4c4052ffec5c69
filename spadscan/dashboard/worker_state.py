"""What the reconstruction side is doing, for the page's one line at the top: a worker at its jobs, jobs whose worker
is gone, jobs that no worker takes, complete scans that no worker has queued, a worker waiting for scans, or no
worker at all.

A worker leaves its traces under the queue: its presence file, renewed while it runs, idle or not
(`<queue>/workers/`, worker/presence.py), the claim files of the jobs it runs and the jobs it queues. A scan or a job
that no worker has picked up within LOOK_S means that no worker serves the root, or that the one there is stuck.
"""

from __future__ import annotations

import datetime as _dt

from .results import age_s

LOOK_S = 20.0
"""A worker looks at the root every 2 s by default (`spadscan worker --poll-s`): a complete scan left without a job, or
a queued job left untaken with no job running, this long means that no worker serves the root."""


def worker_state(rows, jobs: list[dict], now: float, workers: list[dict] = ()) -> dict:
    """{"state": ..., and what the page names}: 'working' (jobs whose worker renews its claim: `jobs`, and `queued`,
    how many wait), 'gone' (running jobs whose worker is gone: `jobs`), 'queued' or 'untaken' (no job running, jobs
    queued: `jobs`, `waited_s` of the one queued longest; 'untaken' from LOOK_S on), 'unqueued' (nothing queued or
    running, complete scans without a job for LOOK_S: `scans`, `waited_s`), 'waiting' (nothing to do, a worker
    present), else 'none' (nothing to do, no worker). Every state also names the workers present (`workers`: "HOST
    pid N" each). `rows`: the scans (ScanRow), `jobs`: the queue's rows (`queue_status`), `now`: time.time(),
    `workers`: the queue's present workers (presence.present_workers)."""
    names = [f"{w['host']} pid {w['pid']}" for w in workers]
    return {**_jobs_state(rows, jobs, now, bool(names)), "workers": names}


def _jobs_state(rows, jobs: list[dict], now: float, present: bool) -> dict:
    running = [j for j in jobs if j["state"] == "running"]
    queued = [j for j in jobs if j["state"] == "queued"]
    working = [j["id"] for j in running if not j.get("stale")]
    if working:
        return {"state": "working", "jobs": working, "queued": len(queued)}
    if running:
        return {"state": "gone", "jobs": [j["id"] for j in running]}
    if queued:
        waited = max(j.get("waiting_s") or 0.0 for j in queued)
        return {"state": "untaken" if waited >= LOOK_S else "queued", "jobs": [j["id"] for j in queued],
                "waited_s": round(waited, 1)}
    return unqueued(rows, {j["scan"] for j in jobs}, now) or {"state": "waiting" if present else "none"}


def unqueued(rows, scans_with_jobs: set, now: float) -> dict | None:
    """The complete scans without a job, finished LOOK_S ago or more (their scan.json's last write), or None."""
    left = [r for r in rows if r.state == "complete" and r.name not in scans_with_jobs and now - r.mtime >= LOOK_S]
    if not left:
        return None
    waited = now - max(r.mtime for r in left)  # of the one finished last
    return {"state": "unqueued", "scans": [r.name for r in left], "waited_s": round(waited, 1)}


def unfollowed(rows, scans_with_jobs: set, now: float) -> list[str]:
    """The scans being recorded (or paused) that have had no job for LOOK_S since they began: a worker started with
    --live queues a scan at its first pose, so a worker present that leaves one does not reconstruct live."""
    return [r.name for r in rows if r.state in ("running", "paused") and r.poses and r.name not in scans_with_jobs
            and (age_s(r.started_utc, _dt.datetime.fromtimestamp(now, _dt.timezone.utc)) or 0.0) >= LOOK_S]

