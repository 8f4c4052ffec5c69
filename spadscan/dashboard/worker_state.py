"""What the reconstruction side is doing, for the page's one line at the top: a worker at its jobs, jobs whose worker
is gone, jobs that no worker takes, complete scans that no worker has queued, a worker waiting for scans, or no
worker at all.

A worker leaves its traces under the queue: its presence file, renewed while it runs, idle or not
(`<queue>/workers/`, worker/presence.py), the claim files of the jobs it runs and the jobs it queues. A scan or a job
that no worker has picked up within LOOK_S means that no worker serves the root, or that the one there is stuck. A job
queued behind others waits for a worker to be free: its wait counts from the later of its queueing and the moment a
claim last began or ended (its attempt records say when), so that a busy worker that takes it at its next look after
finishing the job before never reads as leaving it.

A worker whose job met a full disk claims no job until there is room again, and says so in its presence file
(`room_wait`, disk_room.RoomWait.note); the job it gave back carries the wait in its attempt record, and no worker
claims a job while that room is missing (worker/queue.py `Queue.room_waits`), whether or not a worker says it waits
yet. Where every worker present waits so, or a queued job's wait holds the queue, the queued jobs wait for room, not
for a worker's next look, and the operator is the one to make it. The wait is said in one line as `spadscan ctl` and
the worker's own lines say it (disk_room.room_line: its places, figures and times): the page shows that line.
"""

from __future__ import annotations

import datetime as _dt
import math

from spadscan.worker.disk_room import RoomWait, holding_said, names_said, room_line, size_text

from .results import age_s

LOOK_S = 20.0
"""A worker looks at the root every 2 s by default (`spadscan worker --poll-s`): a complete scan left without a job, or
a queued job left untaken with no job running, this long means that no worker serves the root."""


def worker_state(rows, jobs: list[dict], now: float, workers: list[dict] = (),
                 freed_unix: float | None = None, held=(), start: str | None = None) -> dict:
    """{"state": ..., and what the page names}: 'working' (jobs whose worker renews its claim: `jobs`, and `queued`,
    how many wait), 'gone' (running jobs whose worker is gone: `jobs`), 'queued' or 'untaken' (no job running, jobs
    queued: `jobs`, `waited_s` of the one left longest since a worker could take it; 'untaken' from LOOK_S on),
    'room' (no job running, jobs queued, workers present, and every one of them waits for room on a full disk or a
    queued job's wait holds every claim: `jobs`, `waited_s`), 'unqueued' (nothing queued or running, complete scans
    without a job for LOOK_S: `scans`, `waited_s`), 'waiting' (nothing to do, a worker present), else 'none' (nothing
    to do, no worker). Every state also names the workers present (`workers`: "HOST pid N" each), and where any of
    them waits for room, their waits (`room_waits`); where a queued job's wait holds the queue, those waits
    (`queue_room_waits`); where either is, the line that says it (`room_said`: `wait_line`) and whether it holds the
    queued jobs (`room_holds`: every worker present waits, or the queue is held). Where the queue is held and no
    worker is present, the line says to start one with `start` (the command that starts a worker), and
    `live_room_said` says it as `spadscan ctl` says it of a queued live job (with `--live`).
    `rows`: the scans (ScanRow), `jobs`: the queue's rows (`queue_status`), `now`: time.time(), `workers`: the queue's
    present workers (presence.present_workers), `freed_unix`: when a claim last began or ended
    (attempts.last_claim_change; None: none ever did, or not known), `held`: (job id, its wait) for each queued job
    whose wait for room holds the queue (Queue.room_waits)."""
    names = [worker_name(w) for w in workers]
    state = _jobs_state(rows, jobs, now, bool(names), freed_unix)
    waits = room_waits(workers)
    held = queue_room_waits(held)
    holds = bool(held) or (bool(names) and len(waits) == len(names))
    if holds and names and state["state"] in ("queued", "untaken"):
        state = {**state, "state": "room"}  # no worker takes them at its next look: each waits for room first
    said = wait_line(waits, held, len(names), start=start, now=now)
    live = None
    if held and not names:  # a live job's line names the command `spadscan ctl` gives for it
        live = wait_line(waits, held, 0, start=f"{start or 'spadscan worker'} --live", now=now)
    return {**state, "workers": names, **({"room_waits": waits} if waits else {}),
            **({"queue_room_waits": held} if held else {}),
            **({"room_said": said, "room_holds": holds} if said else {}),
            **({"live_room_said": live} if live else {})}


def worker_name(worker: dict) -> str:
    """A present worker as the page names it: "HOST pid N"."""
    return f"{worker['host']} pid {worker['pid']}"


def room_waits(workers) -> list[dict]:
    """The waits for room of the present workers (presence.present_workers) that wait: each its presence file's
    `room_wait` (exactly disk_room.RoomWait.note's keys: mount, folder, free_bytes, need_bytes, since_unix,
    retry_unix, quota), with `worker` (its name) and the bytes said as the worker's own log says them (`free_said`,
    `need_said`: "12 MB", None where not known). A `room_wait` that is no such note (a damaged file, another
    version's) is no wait: the worker is shown as the rest of its file says."""
    waits = []
    for worker in workers:
        wait = RoomWait.from_note(worker.get("room_wait"), skewed=True)  # (shown: only the queue's gate skips it)
        if wait is None:
            continue
        waits.append({**wait.note(), "worker": worker_name(worker), **_said(wait)})
    return waits


def queue_room_waits(held) -> list[dict]:
    """The waits that hold the queue (`held`: (job id, its wait) as Queue.room_waits gives them): each the wait
    (disk_room.RoomWait.note's keys) with `job`, and its bytes said as `room_waits` says them."""
    read = [(job, note, RoomWait.from_note(note, skewed=True)) for job, note in held]
    return [{**note, "job": job, **_said(wait)} for job, note, wait in read if wait is not None]


def wait_line(waits: list[dict], held: list[dict], present: int, *, start: str | None = None,
              now: float | None = None) -> str | None:
    """The waits for room in one line (disk_room.room_line), or None where there are none. Where they hold the
    queued jobs (every worker present waits: `waits`, `room_waits`'s; or a queued job's wait holds the queue:
    `held`, `queue_room_waits`'s), what `spadscan ctl` says of a queued live job (disk_room.holding_said; `start`:
    the command that starts a worker, said where none is present). Else the workers that wait, by name, and by when
    the first of them claims again (`now`: time.time())."""
    said = holding_said(waits, [(w["job"], w) for w in held], present, start=start, now=now)
    if said is not None:
        return said
    read = [RoomWait.from_note(w, skewed=True) for w in waits]
    if read:
        who = [w["worker"] for w in waits]
        subject = f"the worker on {who[0]} waits" if len(who) == 1 else f"the workers on {names_said(who)} wait"
        return room_line(subject, read, "it" if len(who) == 1 else "the first of them",
                         min(w.retry_unix for w in read), now=now)
    return None


def _said(wait: RoomWait) -> dict:
    """A wait's bytes as the worker's own log says them: {"free_said", "need_said"}: "12 MB", None where not known."""
    return {"free_said": None if wait.free is None else size_text(wait.free),
            "need_said": None if wait.need is None else size_text(wait.need)}


def needs_freed(jobs: list[dict]) -> bool:
    """Whether `worker_state` of the queue's rows `jobs` depends on when a claim last changed (`freed_unix`): no job
    running, and a job queued LOOK_S or longer (a younger one reads 'queued' whenever a worker was free)."""
    return not any(j["state"] == "running" for j in jobs) and any(
        j["state"] == "queued" and (j.get("waiting_s") or 0.0) >= LOOK_S for j in jobs)


def _jobs_state(rows, jobs: list[dict], now: float, present: bool, freed_unix: float | None) -> dict:
    running = [j for j in jobs if j["state"] == "running"]
    queued = [j for j in jobs if j["state"] == "queued"]
    working = [j["id"] for j in running if not j.get("stale")]
    if working:
        return {"state": "working", "jobs": working, "queued": len(queued)}
    if running:
        return {"state": "gone", "jobs": [j["id"] for j in running]}
    if queued:
        # a job queued behind another could be taken no earlier than that one's end
        free_s = math.inf if freed_unix is None else max(0.0, now - freed_unix)
        waited = max(min(j.get("waiting_s") or 0.0, free_s) for j in queued)
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

