"""How a scan ended, as the daemon that held it records it: the one record that `wait`'s reply, `status`'s
`last_scan` and a refused resume read. A scan that ended before the daemon started has none: its folder says how it
ended (`wait` reads its manifest)."""

from __future__ import annotations

from dataclasses import dataclass

ENDED = ("complete", "aborted")
"""The states a scan ends in."""


@dataclass(frozen=True)
class ScanEnd:
    """How one scan ended."""

    state: str
    """complete or aborted."""
    reason: str | None = None
    """Why, where a reason was given: an abort's (`ctl abort --reason`, or the daemon's own), an adaptive scan's early
    end. The daemon's own: a capture whose disk could not take it (an abort kept for a full disk, a folder deleted by
    hand) does not change it."""
    status: dict | None = None
    """The daemon's status as the scan ended (its `status` reply without the daemon's own block); None for a scan
    that ended before this daemon started."""
    at: float | None = None
    """When it ended (time.monotonic()); None with `status`."""


def recorded_end(manifest: dict) -> ScanEnd | None:
    """How a scan ended as its manifest (scan.json, read) records it; None while it has not ended."""
    if manifest.get("state") not in ENDED:
        return None
    return ScanEnd(str(manifest["state"]), str(manifest["reason"]) if manifest.get("reason") else None)
