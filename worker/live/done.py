"""The worker's last word on a live job: once its final result is published, the live status says where, and carries
that result's own figures instead of the live fit's at the scan's end (which an operator would read as the result)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Callable

from spadscan.protocol.capture_format import fold
from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.live_status import (LiveStatus, is_chamfer, is_count, read_status, status_path,
                                           write_status)

from ..jobs import Job, scan_path


def mark_live_done(job: Job, root: Path, result: Path, log: Callable[[str], None]) -> None:
    """Set `<scan>/recon/live/status.json` to state 'done' naming `result` (the published result folder), with the
    final result's figures (`done_status`). A live status that cannot be read is left alone (the result itself is in
    place either way)."""
    try:
        path = status_path(scan_path(job, root))
        status = read_status(path)
        if not holds(status, job):
            return  # another live job's folder (`holds`): this job's result is in its own folder, not there
        write_status(path.parent, dataclasses.replace(done_status(status, Path(result)), job=job.id))
    except (SpadscanError, OSError) as exc:
        log(f"{job.id}: its result is published, but the live status was not updated: {exc}")


def mark_live_done_unsaid(job: Job, root: Path, result: Path, log: Callable[[str], None]) -> None:
    """`mark_live_done` for a job found done when a worker starts, unless its live status says 'done' already: its
    worker died after moving the job to done/ and before it said so there. A status that is missing or cannot be
    read is left alone without a word (the job was settled long ago, or its scan's live folder removed)."""
    try:
        status = read_status(status_path(scan_path(job, root)))
    except (SpadscanError, OSError):
        return
    if status.state != "done":
        mark_live_done(job, root, result, log)


def mark_live_failed(job: Job, root: Path, error: str, log: Callable[[str], None]) -> None:
    """Set `<scan>/recon/live/status.json` to state 'stopped' with `error` as its note, for a live job the queue has
    given up on: the job process can die, or its final run fail, after it wrote 'final' ("finishing"), which would
    then stand for good. A status that already says how the job ended ('done', 'aborted', 'stopped': the job's own
    word, more precise), another job's (`holds`) or one that cannot be read is left alone."""
    try:
        path = status_path(scan_path(job, root))
        status = read_status(path)
        if holds(status, job) and status.state not in ENDED:
            write_status(path.parent, dataclasses.replace(status, state="stopped", note=" ".join(error.split()),
                                                          updated_utc="", figures_utc=figures_time(status)))
    except (SpadscanError, OSError) as exc:
        log(f"{job.id}: the live status was not updated: {exc}")


AGAIN = ("the job is back in the queue and runs again from the start when a worker claims it; the figures and "
         "picture here are the stopped attempt's")
"""What the live status of a job given back to the queue says after why."""


def mark_live_queued(job, root: Path, why: str, log: Callable[[str], None], ended_too: bool = False) -> None:
    """Set a live job's `<scan>/recon/live/status.json` to 'queued', its note `why` and then AGAIN: the job went back
    to the queue before it ended, and its status would otherwise go on saying it is finishing (or following the
    scan) with no process running it. Its figures stay, as the mesh and preview beside them: the stopped attempt's,
    which the next attempt begins afresh. A status that is missing (the job was stopped before it wrote one), another
    job's or one that says how the job ended is left alone; one that cannot be read or written is too, saying so in
    the log. `ended_too`: a status that says how the job ended is set to 'queued' too, and its `result` dropped
    (`spadscan worker --redo` and `--retry-failed` queue a finished or failed job again: its 'done' or 'stopped'
    would otherwise stand, with the figures of a result moved aside, until a worker claims it)."""
    if not job.live:
        return
    try:
        path = status_path(scan_path(job, root))
        if not path.is_file():
            return
        status = read_status(path)
        if status.job == job.id and same_owner(status, job) and (ended_too or status.state not in ENDED):
            write_status(path.parent, dataclasses.replace(status, state="queued", note=f"{fold(why)}; {AGAIN}",
                                                          updated_utc="", figures_utc=figures_time(status),
                                                          result=None if ended_too else status.result))
    except (SpadscanError, OSError) as exc:
        log(f"{job.id}: the live status was not updated: {fold(exc)}")


def figures_time(status: LiveStatus) -> str | None:
    """When `status`'s figures were measured: its own `figures_utc` where it was rewritten without them already,
    else its `updated_utc`. A status given back or stopped is written anew (its update is the give-back's) and keeps
    the stopped attempt's figures: with their own time, they are never read as the job's now."""
    return status.figures_utc or status.updated_utc or None


def holds(status: LiveStatus, job) -> bool:
    """Whether the live folder whose status is `status` is `job`'s: the folder (`<scan>/recon/live/`, one per scan)
    is the first live job's that took it (`worker.live.publish.take_live_folder`), and only that job writes there.
    Another live job of the scan (another id: a hashed one, another preset) never ends, fails or queues the one
    that holds it, nor does another queue's live job of the same id (on the same root), told apart by its owner
    token (`same_owner`). A status naming no job (written by an earlier version) is taken to be the job's."""
    return status.job in ("", job.id) and same_owner(status, job)


def same_owner(status: LiveStatus, job) -> bool:
    """Whether `status` was written by `job` as its owner token says (`Job.owner`, `LiveStatus.owner`): a status
    or a job without one (an earlier version's) is told by the job's id alone."""
    owner = getattr(job, "owner", "")
    return not status.owner or not owner or status.owner == owner


ENDED = ("done", "aborted", "stopped")
"""Live states that say how the job ended."""

SCAN_ABORTED = "scan aborted by the operator: nothing to retry"
"""How a live job that ended because its scan was aborted is recorded and said: failed in the queue (its only end
short of done), but no fault to fix, and a retry would follow a scan that publishes nothing more."""


def done_status(status: LiveStatus, result: Path) -> LiveStatus:
    """`status` as 'done' with `result`, the figures those of the result's report.json: the views the final run
    fitted (every published one), its steps (on top of the live fit's where it continued from the live fit; alone
    where it started from the carved hull, which the live steps did not shape), its convergence and its Chamfer (None
    when it has none: the live fit's would read as the result's), measured on the result's own mesh of all those
    views (no `chamfer_views`: the live mesh's count would name the wrong mesh). Where that report cannot be read,
    the live fit's figures stay, its `chamfer_views` with them. The live mesh's warnings go: the result's own report
    says its doubts."""
    done = dataclasses.replace(status, state="done", result=str(result), updated_utc="", warnings=(), figures_utc=None)
    try:
        report = json.loads((result / "report.json").read_text())
    except (OSError, ValueError):
        return done
    if not isinstance(report, dict):
        return done
    steps = report.get("steps")
    chamfer = report.get("chamfer_mm")
    scene = report.get("scene")
    views = scene.get("views") if isinstance(scene, dict) else None
    live = report.get("live")
    before = 0 if isinstance(live, dict) and live.get("final_start") == "hull" else status.steps
    return dataclasses.replace(
        done, views_used=views if is_count(views) else status.views_published,
        steps=before + steps if is_count(steps) else status.steps,
        converged=report.get("converged") is True,
        chamfer_mm=float(chamfer) if is_chamfer(chamfer) else None, chamfer_views=None)


__all__ = ["mark_live_done", "mark_live_done_unsaid", "mark_live_failed", "mark_live_queued", "done_status",
           "holds", "same_owner", "SCAN_ABORTED"]
