"""`<capture>/recon/live/status.json`: what a live reconstruction has done so far, for people and for `spadscan ctl`.

A live job (`spadscan worker --live`) follows a scan while it is recorded and rewrites this file every few seconds,
beside the mesh and the preview it publishes (`recon/live/mesh.ply`, `recon/live/preview.png`). Every file there is
written to a hidden temporary name and renamed into place, the status last: a reader sees a whole file, never a
torn one, and a status no newer than the mesh beside it.

The format is a JSON object; readers accept unknown keys. Standard library only: the daemon-side client
(`spadscan ctl`) reads it without loading numpy or the worker.

Keys (metres and seconds as everywhere; the Chamfer in millimetres, as people read it):

- `views_used` (int >= 0): views (poses) the live model is fitting;
- `views_published` (int >= 0): views of the scan published so far (the model may lag behind by a few);
- `steps` (int >= 0): optimisation steps the live job has taken over all its models;
- `updated_utc` (string): when this status was written, ISO 8601 UTC with milliseconds;
- `converged` (bool): the live model's fit has plateaued on the views it has;
- `chamfer_mm` (number): Chamfer distance of the published mesh to the ground truth; only when the capture names
  one;
- `chamfer_views` (int >= 0): the views of the fit that mesh was made from, when the status has been rewritten
  since (after a refit, or every few seconds) and the fit holds more now; absent otherwise;
- `state` (string): `waiting` (too few views yet), `live` (following the scan), `final` (the scan is complete: the
  final reconstruction runs from the live state), `done` (the final result is published: `result`), `aborted` (the
  scan was aborted; the job ended), `stopped` (the job ended otherwise: `note`) or `queued` (the job is back in the
  queue before it ended: its worker was stopped or died, or its process crashed and it is retried; `note` says
  which; the figures, mesh and preview are the stopped attempt's until the next attempt starts, which begins them
  afresh);
- `views_planned` (int or null): poses the scan plans, when the capture says;
- `job` (string): the queue's job id;
- `owner` (string, absent when none): the live job's own token (its job file's `owner`, random, given when it was
  queued): two queues on one root give a scan's live job one id, and the token says which of the two holds this
  folder; a status without one is taken to be that of any job of its id;
- `result` (string or null): the final result folder, once `done`;
- `note` (string or null): one line worth knowing (why the job ended, why it waits);
- `warnings` (list of strings, absent when empty): one line per doubt about what is published here, as a run's
  report.json says them (`the histograms are saturated (...)`: most histograms of the views fitted are saturated
  by pile-up, said while the scan runs so that the power can be lowered or the sensor moved back; `no preview.png:
  <why>`: the live mesh's preview could not be drawn);
- `final_start` (`live`, `hull` or absent): from state `final` on, where the final run starts: from the live fit, or
  from the carved hull (a live fit still too young, or lagging the scan);
- `figures_utc` (string or absent): when the figures (views, steps, Chamfer) were measured, where the status was
  written again later without measuring them: a job given back to the queue (`queued`) or stopped by its worker
  (`stopped`) keeps the stopped attempt's figures, which are that attempt's, of this time, never the job's now.

Once `done`, the figures are the final result's (its report.json): `views_used` the views it fitted, `steps` the
final run's on top of the live fit's where it continued from it (its own alone from the hull), `converged` and
`chamfer_mm` its own (no `chamfer_mm` when it has none), measured on its mesh of all `views_used`: no
`chamfer_views` (the live mesh's count would name the wrong mesh).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from .atomic_files import write_atomic
from .errors import CaptureError
from .iso_time import parse_utc, utc_now

LIVE_DIR = "live"
"""The live results' folder under a capture's `recon/`."""
STATUS = "status.json"
STATES = ("waiting", "live", "final", "done", "aborted", "stopped", "queued")
FINAL_STARTS = ("live", "hull")
"""Where a live job's final run starts (`final_start`): from the live fit, or from the carved hull."""
SAID = {"waiting": "waiting for views", "live": "following the scan", "final": "finishing", "done": "done",
        "aborted": "ended (the scan was aborted)", "stopped": "stopped", "queued": "queued again"}
"""Each state as people read it."""


@dataclass(frozen=True)
class LiveStatus:
    """One status of a live reconstruction (see the module for each field)."""

    views_used: int
    views_published: int
    steps: int
    converged: bool = False
    state: str = "live"
    updated_utc: str = ""
    chamfer_mm: float | None = None
    views_planned: int | None = None
    job: str = ""
    result: str | None = None
    note: str | None = None
    final_start: str | None = None
    chamfer_views: int | None = None
    """The views of the fit whose mesh `chamfer_mm` was measured on: the status is rewritten between two meshes, and
    the fit has grown since (None: `views_used`'s)."""
    warnings: tuple[str, ...] = ()
    """Doubts about what is published beside it, one line each (a tuple: the status is frozen)."""
    figures_utc: str | None = None
    """When the figures were measured, where the status was rewritten since without them (the stopped attempt's
    figures of a job given back or stopped: `earlier_figures`); None: they are of `updated_utc`."""
    owner: str = ""
    """The live job's token (its job file's `owner`): which of two live jobs of one id holds the folder."""

    def to_dict(self) -> dict:
        """The JSON object written; `chamfer_mm`, `final_start`, `chamfer_views`, `figures_utc`, `warnings` and
        `owner` only when there is one."""
        data = asdict(self)
        if not data["owner"]:
            del data["owner"]
        for key in ("chamfer_mm", "final_start", "chamfer_views", "figures_utc"):
            if data[key] is None:
                del data[key]
        data["warnings"] = list(self.warnings)
        if not data["warnings"]:
            del data["warnings"]
        return data

    def updated(self) -> _dt.datetime | None:
        """`updated_utc` as an aware time (UTC when it names no zone); None when it cannot be read (`parse_utc`)."""
        return parse_utc(self.updated_utc)

    def age_s(self, now: _dt.datetime | None = None) -> float | None:
        """Seconds since `updated_utc` (None when it cannot be read)."""
        then = self.updated()
        if then is None:
            return None
        return max(0.0, ((now or _dt.datetime.now(_dt.timezone.utc)) - then).total_seconds())

    def earlier_figures(self) -> bool:
        """Whether the figures are a stopped attempt's, not the job's now: the job was given back to the queue (its
        next attempt begins afresh) or stopped (`figures_utc`, where given, says when they were measured)."""
        return self.state in ("queued", "stopped")

    def figures_said(self, now: _dt.datetime | None = None) -> str:
        """When a stopped attempt's figures were measured ('as of 2026-12-03 17:29:55 UTC, 95 s ago'), or that they
        are not the job's now where the status does not say (one written by an earlier version)."""
        then = parse_utc(self.figures_utc)
        if then is None:
            return "not the job's now"
        age = max(0.0, ((now or _dt.datetime.now(_dt.timezone.utc)) - then).total_seconds())
        return f"as of {then.astimezone(_dt.timezone.utc):%Y-%m-%d %H:%M:%S} UTC, {age:.0f} s ago"

    def figures(self, now: _dt.datetime | None = None) -> list[str]:
        """The figures as people read them, in one wording wherever they are shown (`summary`, the demo's progress
        line): views used of published (of planned), steps, converged, Chamfer. A stopped attempt's figures
        (`earlier_figures`) are said to be that attempt's, as of their own time where the status gives it: the
        status's update is the give-back's, and beside it they would read as the job's now. A status with no figures
        yet (nothing fitted, no Chamfer) is not said to hold a stopped attempt's."""
        planned = f" of {self.views_planned} planned" if self.views_planned else ""
        parts = [f"{self.views_used}/{self.views_published} views{planned}", f"{self.steps} steps"]
        if self.converged:
            parts.append("converged")
        if self.chamfer_mm is not None:
            # A done status's Chamfer is its result's, on all its views (one written by an earlier version may
            # still carry the live mesh's count).
            on = (f" (its mesh of {self.chamfer_views} views)"
                  if self.chamfer_views not in (None, self.views_used) and self.state != "done" else "")
            parts.append(f"Chamfer {self.chamfer_mm:.2f} mm{on}")
        if self.earlier_figures() and (self.views_used or self.steps or self.chamfer_mm is not None):
            parts[0] = f"the stopped attempt's {parts[0]}"
            parts[-1] += f" ({self.figures_said(now)})"
        return parts

    def summary(self, now: _dt.datetime | None = None) -> str:
        """One line for people: state, the figures (`figures`), last update, note and warnings."""
        parts = self.figures(now)
        age = self.age_s(now)
        if age is not None:
            parts.append(f"updated {age:.0f} s ago")
        if self.note:
            parts.append(self.note)
        parts += self.warnings
        return f"live reconstruction {SAID.get(self.state, self.state)}: " + ", ".join(parts)


def status_path(capture) -> Path:
    """`<capture>/recon/live/status.json`."""
    return Path(capture) / "recon" / LIVE_DIR / STATUS


def write_status(folder, status: LiveStatus) -> Path:
    """Write `status` as `folder/status.json` (a temporary file renamed over it); `updated_utc` is set to now when
    empty. Returns the path."""
    if not status.updated_utc:
        status = LiveStatus(**{**asdict(status), "updated_utc": utc_now()})
    check_status(status, "live status")
    return write_atomic(Path(folder) / STATUS, (json.dumps(status.to_dict(), indent=1) + "\n").encode())


def read_status(path) -> LiveStatus:
    """The status in `path` (a status.json, or a capture folder); CaptureError in one line when it is missing or
    malformed."""
    path = Path(path)
    if path.is_dir():
        path = status_path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CaptureError(f"{path}: no live status") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise CaptureError(f"{path}: unreadable live status ({exc})") from None
    if not isinstance(data, dict):
        raise CaptureError(f"{path}: a live status is a JSON object")
    known = {f.name for f in fields(LiveStatus)}
    missing = sorted({"views_used", "views_published", "steps"} - set(data))
    if missing:
        raise CaptureError(f"{path}: live status lacks {', '.join(missing)}")
    given = {k: v for k, v in data.items() if k in known}
    if isinstance(given.get("warnings"), list):
        given["warnings"] = tuple(given["warnings"])
    status = LiveStatus(**given)
    check_status(status, str(path))
    return status


def check_status(status: LiveStatus, where: str) -> None:
    """CaptureError naming `where` and the field when a status holds what its format does not allow."""
    for key in ("views_used", "views_published", "steps"):
        value = getattr(status, key)
        if not is_count(value):
            raise CaptureError(f"{where}: {key} {value!r} must be an integer >= 0")
    for key in ("views_planned", "chamfer_views"):
        value = getattr(status, key)
        if value is not None and not is_count(value):
            raise CaptureError(f"{where}: {key} {value!r} must be an integer >= 0 or null")
    if not isinstance(status.converged, bool):
        raise CaptureError(f"{where}: converged {status.converged!r} must be true or false")
    if status.state not in STATES:
        raise CaptureError(f"{where}: state {status.state!r} must be one of {', '.join(STATES)}")
    if status.chamfer_mm is not None and not is_chamfer(status.chamfer_mm):
        raise CaptureError(f"{where}: chamfer_mm {status.chamfer_mm!r} must be a finite number >= 0")
    for key in ("updated_utc", "job", "owner"):
        if not isinstance(getattr(status, key), str):
            raise CaptureError(f"{where}: {key} {getattr(status, key)!r} must be a string")
    for key in ("result", "note", "figures_utc"):
        value = getattr(status, key)
        if value is not None and not isinstance(value, str):
            raise CaptureError(f"{where}: {key} {value!r} must be a string or null")
    if not isinstance(status.warnings, tuple) or not all(isinstance(w, str) for w in status.warnings):
        raise CaptureError(f"{where}: warnings {status.warnings!r} must be a list of strings")
    if status.final_start is not None and status.final_start not in FINAL_STARTS:
        raise CaptureError(f"{where}: final_start {status.final_start!r} must be one of {', '.join(FINAL_STARTS)}")


def is_count(value) -> bool:
    """Whether `value` is what a count field holds: an integer >= 0 (a JSON true is not one)."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def is_chamfer(value) -> bool:
    """Whether `value` is what `chamfer_mm` holds when present: a finite number >= 0."""
    return (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            and value >= 0)


__all__ = ["LiveStatus", "LIVE_DIR", "STATUS", "STATES", "status_path", "write_status", "read_status",
           "check_status", "is_count", "is_chamfer"]
