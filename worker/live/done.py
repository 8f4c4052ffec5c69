"""The worker's last word on a live job: once its final result is published, the live status says where."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.live_status import read_status, status_path, write_status

from ..jobs import Job, scan_path


def mark_live_done(job: Job, root: Path, result: Path, log: Callable[[str], None]) -> None:
    """Set `<scan>/recon/live/status.json` to state 'done' naming `result` (the published result folder). A live
    status that cannot be read is left alone (the result itself is in place either way)."""
    try:
        path = status_path(scan_path(job, root))
        status = read_status(path)
        write_status(path.parent, dataclasses.replace(status, state="done", result=str(result), updated_utc=""))
    except (SpadscanError, OSError) as exc:
        log(f"{job.id}: its result is published, but the live status was not updated: {exc}")


__all__ = ["mark_live_done"]
