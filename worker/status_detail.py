"""The last column of `spadscan worker --status` for one job (and the dashboard's queue table, which shows the same):
a done job's result folder and what its report said of itself, a running job's progress, else its last error, then
damaged queue files."""

from __future__ import annotations

import json
from pathlib import Path

from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.live_status import read_status, status_path

ENDED = ("done", "aborted", "stopped")
"""Live states after which the job's line is no longer the live status's (its final run has a bar, or it ended)."""


def result_health(row) -> dict:
    """{"converged": bool, "warnings": [...]} from a done job's report.json (what its reconstruction said about
    itself); {} when there is none to read."""
    if row.state != "done" or not row.result:
        return {}
    try:
        report = json.loads((Path(row.result) / "report.json").read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(report, dict):
        return {}
    warnings = report.get("warnings")
    return {"converged": report.get("converged"),
            "warnings": [str(w) for w in warnings] if isinstance(warnings, list) else []}


def live_detail(root, row) -> str | None:
    """A running live job's line from its scan's live status (`<scan>/recon/live/status.json`, which it rewrites as
    it follows the scan: its log shows no progress bar until its final run), or None; `root`: the captures root."""
    if root is None or row.state != "running":
        return None
    try:
        status = read_status(status_path(Path(root) / row.scan))
    except (SpadscanError, OSError):
        return None
    # 'queued': the given-back attempt's last word, until the attempt that took the job over writes its own
    return status.summary() if status.job == row.id and status.state not in (*ENDED, "queued") else None


def status_detail(row, running: dict | None = None, root=None) -> str:
    """The last column of a --status row: a done job's result folder, a running job's progress (its log's progress
    bar, `running`: job_progress.running_progress; a live job's live status while it follows its scan, `root`: the
    captures root), else its last error; then damaged files. A stale running job's row says why first."""
    if row.state == "done":
        detail = row.result or f"result: unknown ({'; '.join(row.notes) or 'no attempt record'})"
        if row.result and row.kept:
            detail += " (already there when the job was claimed: kept, not run)"
        if row.result and not Path(row.result).exists():
            detail += " (no longer there)"  # its scan moved out of the root (archived), or the folder removed
        health = result_health(row)
        if health.get("converged") is False:
            detail += " (not converged)"
        notes = [f"warning: {w}" for w in health.get("warnings", [])] + ([] if not row.result else row.notes)
    else:
        progress = (running or {}).get(row.id) if row.state == "running" else None
        detail, notes = (progress.line() if progress else live_detail(root, row) or row.error or "-"), row.notes
        if progress and row.error:
            notes = [f"last error: {row.error}", *notes]
        if row.stale:
            detail, notes = row.stale, [n for n in [row.error, *notes] if n]
    return "; ".join([detail, *notes])
