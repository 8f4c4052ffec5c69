"""The last column of `spadscan worker --status` for one job (the dashboard's queue table shows the same, its
warnings counted rather than listed): a done job's result folder and what its report said of itself, a running job's
progress, else its last error, then damaged queue files."""

from __future__ import annotations

import json
from pathlib import Path

from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.live_status import STATES, LiveStatus, read_status, status_path

from .live.done import same_owner

ENDED = ("done", "aborted", "stopped")
"""Live states after which the job's line is no longer the live status's (its final run has a bar, or it ended)."""
FOLLOWING = tuple(s for s in STATES if s not in (*ENDED, "queued"))
"""Live states of a job that follows its scan or runs its final run (not one that ended or was given back)."""


def result_health(row) -> dict:
    """{"converged": bool, "warnings": [...], "chamfer_mm": mm or None} from a done job's report.json (what its
    reconstruction said about itself, and its figure where the scan has a ground truth); {} when there is none to
    read."""
    if row.state != "done" or not row.result:
        return {}
    try:
        report = json.loads((Path(row.result) / "report.json").read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(report, dict):
        return {}
    warnings = report.get("warnings")
    chamfer = report.get("chamfer_mm")
    return {"converged": report.get("converged"),
            "warnings": [str(w) for w in warnings] if isinstance(warnings, list) else [],
            "chamfer_mm": chamfer if isinstance(chamfer, (int, float)) and not isinstance(chamfer, bool) else None}


def live_detail(root, row) -> str | None:
    """A running live job's line from its scan's live status (`<scan>/recon/live/status.json`, which it rewrites as
    it follows the scan: its log shows no progress bar until its final run), or None; `root`: the captures root."""
    if row.state != "running":
        return None
    status = own_live_status(root, row)
    return status.summary() if status is not None else None


def own_live_status(root, job, states: tuple[str, ...] = FOLLOWING) -> LiveStatus | None:
    """The live status (`<scan>/recon/live/status.json`) of live job `job` (a Job or a --status row: its id, scan
    and owner token) when it is in one of `states` (by default FOLLOWING: while it follows its scan or runs its final
    run); None when there is none, it cannot be read, it is another job's (another id, or another queue's job of the
    same id, told apart by its owner token: `same_owner`; such a job runs as an ordinary one once the scan has ended,
    and its row must not show the other's progress), or it is in another state (by default: past, ENDED, or a
    given-back attempt's last word, 'queued', until the attempt that took the job over writes its own); `root`: the
    captures root."""
    if root is None:
        return None
    try:
        status = read_status(status_path(Path(root) / job.scan))
    except (SpadscanError, OSError):
        return None
    return status if status.job == job.id and same_owner(status, job) and status.state in states else None


def status_lines(row, running: dict | None = None, root=None) -> list[str]:
    """The last column of a --status row for a terminal: the row's own line (`status_parts`' detail and notes, a
    done job's warnings counted), then each warning on a line of its own, "warning: ..." (a report gives up to
    about ten, each a sentence or two: on the row's line they made one line of thousands of characters)."""
    detail, warnings, notes = status_parts(row, running, root)
    if warnings:
        detail += f" ({len(warnings)} warning{'s' if len(warnings) != 1 else ''} below)"
    return ["; ".join([detail, *notes]), *(f"warning: {w}" for w in warnings)]


def status_parts(row, running: dict | None = None, root=None) -> tuple[str, list[str], list[str]]:
    """(detail, warnings, notes) of a --status row: a done job's result folder, a running job's progress (its log's
    progress bar, `running`: job_progress.running_progress; a live job's live status while it follows its scan,
    `root`: the captures root), else its last error; a done job's report's warnings; then damaged files. A stale
    running job's row says why first."""
    warnings: list[str] = []
    if row.state == "done":
        detail = row.result or f"result: unknown ({'; '.join(row.notes) or 'no attempt record'})"
        if row.result and row.kept:
            detail += " (already there when the job was claimed: kept, not run)"
        if row.result and not Path(row.result).exists():
            detail += " (no longer there)"  # its scan moved out of the root (archived), or the folder removed
        health = result_health(row)
        if health.get("chamfer_mm") is not None:
            detail += f" (Chamfer to the ground truth {health['chamfer_mm']:.2f} mm)"
        if health.get("converged") is False:
            detail += " (not converged)"
        warnings = health.get("warnings", [])
        notes = [] if not row.result else row.notes
    else:
        progress = (running or {}).get(row.id) if row.state == "running" else None
        detail, notes = (progress.line() if progress else live_detail(root, row) or row.error or "-"), row.notes
        if progress and row.error:
            notes = [f"last error: {row.error}", *notes]
        if row.stale:
            detail, notes = row.stale, [n for n in [row.error, *notes] if n]
    return detail, warnings, notes
