"""What the reconstruction side is doing, for the page's one line at the top: a worker at its jobs, jobs whose worker
is gone, jobs that no worker takes, complete scans that no worker has queued, or nothing at all.

A worker leaves a trace under the root only through the queue: the claim files of the jobs it runs, renewed every few
seconds (`<queue>/running/<job>~<claim>.json`), and the jobs it queues. A worker with nothing to do writes nothing,
so it cannot be told from no worker at all; a scan or a job that no worker has picked up within LOOK_S can.
"""

from __future__ import annotations

import shlex
from pathlib import Path

from spadscan.worker.queue import QUEUE_DIRNAME

LOOK_S = 20.0
"""A worker looks at the root every 2 s by default (`spadscan worker --poll-s`): a complete scan left without a job, or
a queued job left untaken with no job running, this long means that no worker serves the root."""


def worker_state(rows, jobs: list[dict], now: float) -> dict:
    """{"state": ..., and what the page names}: 'working' (jobs whose worker renews its claim: `jobs`, and `queued`,
    how many wait), 'gone' (running jobs whose worker is gone: `jobs`), 'queued' or 'untaken' (no job running, jobs
    queued: `jobs`, `waited_s` of the one queued longest; 'untaken' from LOOK_S on), 'unqueued' (nothing queued or
    running, complete scans without a job for LOOK_S: `scans`, `waited_s`), else 'idle'. `rows`: the scans (ScanRow),
    `jobs`: the queue's rows (`queue_status`), `now`: time.time()."""
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
    return unqueued(rows, {j["scan"] for j in jobs}, now) or {"state": "idle"}


def unqueued(rows, scans_with_jobs: set, now: float) -> dict | None:
    """The complete scans without a job, finished LOOK_S ago or more (their scan.json's last write), or None."""
    left = [r for r in rows if r.state == "complete" and r.name not in scans_with_jobs and now - r.mtime >= LOOK_S]
    if not left:
        return None
    waited = now - max(r.mtime for r in left)  # of the one finished last
    return {"state": "unqueued", "scans": [r.name for r in left], "waited_s": round(waited, 1)}


def start_command(root: Path, queue_dir: Path) -> str:
    """The command that starts a worker on `root` (and its queue, when it is not the default one)."""
    words = ["spadscan", "worker", "--root", str(Path(root).resolve())]
    if Path(queue_dir).resolve() != Path(root).resolve() / QUEUE_DIRNAME:
        words += ["--queue", str(queue_dir)]
    return shlex.join(words)
