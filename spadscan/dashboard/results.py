"""The reconstructions of a scan as the dashboard lists them: each finished job's results folder
(`<scan>/recon/<job>/`, its report.json summed up, links to report.html, preview.png and view3d.html) and the live
one while a scan is reconstructed as it runs (`<scan>/recon/live/`: status.json, preview.png, mesh.ply).

Folders are remembered by their modification times, like the scans (scans.py).

Once a live job is done, its status carries its final result's figures, while its mesh and preview stay the live
fit's last (worker/live/done.py): the live entry then gives way to that result (listed first, `from_live`), so that no
figures are shown over the picture of another fit. Each live entry says its state, note and age (`age_s`, seconds
since its status was written): one whose worker stopped must not look like one that runs.

A result with a mesh and no preview says why where its report does (`no_preview`): the worker draws the preview on
its own machine, which may not be the dashboard's.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
from pathlib import Path

from spadscan.protocol.iso_time import parse_utc
from spadscan.protocol.live_status import FINAL_STARTS

from .paths import safe_path, url_path

RECON = "recon"
LIVE = "live"
SUMMARY_KEYS = ("preset", "method", "chamfer_mm", "accuracy_mm", "completeness_mm", "fscore_5mm", "normal_error_deg",
                "steps", "seconds", "stopped_by", "converged", "warnings", "capture_state", "ground_truth_note")
LIVE_KEYS = ("views_used", "views_published", "views_planned", "steps", "updated_utc", "converged", "chamfer_mm",
             "state", "note", "result", "job", "final_start", "chamfer_views", "warnings", "figures_utc")
LIVE_PICTURES = ("preview.png", "mesh.ply", "view3d.html")
"""The live entry's files that show the live fit's shape (not the final result's)."""
PAGES = ("report.html", "preview.png", "view3d.html", "error_vs_time.png", "coverage.png", "mesh.ply")
SERIOUS = tuple(re.compile(p) for p in (
    r"^the fit does not explain the measurements",
    r"^\d+ % of the surface .* was seen by fewer than",
    r"^the mesh is in \d+ pieces",
    r"^\d+ specks stand apart from the mesh",
    r"^the mesh has \d+ tunnels",
    r"^too little signal",
    r"^faint returns",
    r"^the histograms are saturated",
    r"^[\d.]+ % of the first returns that can have come from the object",
    r"^views as near as \d+ mm to the scene's centre keep its bound",
    r"^the floor at z = .* cuts the object",
    r"^the object is dark",
    r"^the \d+ views all look down",
    r"^the \d+ views all stand .* on one ring",
    r"^the \d+ views all stand .* none higher",
    r"^the views' returns lie [\d.]+ m away",
    r"^the object is small against the sensor's view",
    r"^too much ambient light",
    r"^no view looked above the mesh's top",
    r"^the mesh stops [\d.]+ cm above the floor",
))
"""The starts of the end-of-run warnings (worker/end_of_run.py, worker/signal_check.py, the scene's notes) that
doubt the shape itself: the fit does not explain the measurements, too few views saw the surface, the mesh is in
pieces, specks or tunnels, misses a part that returns came from, the capture holds too little signal, or is saturated
by pile-up or buried under ambient light, the scene's bound or the floor cuts the object, the object is dark or
small against the sensor's view, the views all look down, stand on one ring or low down only, stand far away or
never looked above the mesh's top, or the mesh stops above its floor. The others say how the run went (stopped on its
budget, a busy machine): a longer run mends them."""
OFF_SCREEN = "off screen"
"""Words of the worker's reason where its machine cannot draw pictures (worker/report/offscreen.py
`OffscreenUnavailable`: "no display and no EGL or OSMesa library to draw meshes off screen: install ...")."""
WORKER_CANNOT_DRAW = "no preview: the worker's machine could not draw off screen"
"""What the page says of a result whose report says that the machine its worker ran on could not draw off screen."""


def _read_json(path: Path) -> tuple[dict | None, str | None]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        return None, f"{path.name}: {' '.join(str(exc).split())}"
    return (data, None) if isinstance(data, dict) else (None, f"{path.name}: not a JSON object")


class ResultIndex:
    """Reconstruction folders of the scans under one root, remembered between polls."""

    def __init__(self, root):
        self.root = Path(root)
        self.reads = 0
        self._folders: dict[str, tuple[tuple, dict]] = {}

    def for_scan(self, scan: str, now: _dt.datetime | None = None) -> list[dict]:
        """The scan's reconstructions: the live one first, then finished ones, newest first; a live one that is done
        gives way to its result, then listed first with `from_live` (`fold_done_live`). Each: id, kind ('live' or
        'final'), files (URL paths under /files/ of those present), summary or status, error; a live one also
        `age_s`, the seconds since its status was written (None when that time cannot be read)."""
        recon = self.root / scan / RECON
        try:
            names = [e.name for e in os.scandir(recon) if e.is_dir() and not e.name.startswith(".")
                     and ".replaced-" not in e.name]
        except OSError:
            return []
        found = [self._folder(scan, recon / name) for name in names]
        found = [f for f in found if f is not None]
        found.sort(key=lambda f: (f["kind"] != LIVE, -f["mtime"]))
        now = now or _dt.datetime.now(_dt.timezone.utc)
        # figures_age_s: the age of a stopped attempt's figures that a status given back or stopped keeps (its
        # `figures_utc`), None where it has none
        found = [{**f, "age_s": age_s(f["summary"].get("updated_utc"), now),
                  "figures_age_s": age_s(f["summary"].get("figures_utc"), now)} if f["kind"] == LIVE else f
                 for f in found]
        return fold_done_live(found)

    def _folder(self, scan: str, folder: Path) -> dict | None:
        live = folder.name == LIVE
        main = folder / ("status.json" if live else "report.json")
        try:
            st = main.stat()
        except OSError:
            return None  # nothing published there yet
        key = (st.st_mtime_ns, st.st_size, tuple((folder / p).exists() for p in PAGES))
        cached = self._folders.get(str(folder))
        if cached and cached[0] == key:
            return cached[1]
        self.reads += 1
        data, error = _read_json(main)
        keys = LIVE_KEYS if live else SUMMARY_KEYS
        summary = {k: data[k] for k in keys if data and k in data}
        start = None if live else final_start(data)
        if start is not None:
            summary["final_start"] = start
        if not isinstance(summary.get("warnings", []), list):
            # the page lists them one a line: anything else would stop its whole refresh, every scan with it
            error = f"{main.name}: warnings {json.dumps(summary.pop('warnings'))[:40]} is not a list"
        if summary.get("warnings"):
            summary["warning_levels"] = [warning_level(w) for w in summary["warnings"]]
        # a link only to what the server serves (safe_path): never one to a folder linked out of the root
        # Each file versioned by its own time: a live status is rewritten every few seconds between two meshes,
        # and a version of its time would have the page reload the same preview and 3D view as often.
        files = {p: f"/files/{rel}?v={_mtime_ns(folder / p)}"
                 for p in PAGES if safe_path(self.root, rel := url_path(scan, RECON, folder.name, p))}
        if live and "mesh.ply" in files:  # the server makes the live view from that very mesh
            files["view3d.html"] = f"/live3d/{url_path(scan)}?v={_mtime_ns(folder / 'mesh.ply')}"
        if live and summary.get("state") == "done":
            # its figures are the final result's, its mesh and preview the live fit's last: never one over the other
            files = {p: url for p, url in files.items() if p not in LIVE_PICTURES}
        entry = {"id": folder.name, "scan": scan, "kind": LIVE if live else "final", "mtime": st.st_mtime,
                 "summary": summary, "error": error, "files": files}
        if not live:
            # A live job's result records its live fit (`live`, worker/live/job.py) from the first version on; one
            # without it is an ordinary job's, or a live job's that never fitted and ran from scratch. None: unread.
            entry["live_record"] = None if data is None else isinstance(data.get("live"), dict)
        if "mesh.ply" in files and "preview.png" not in files:
            entry["no_preview"] = no_preview(summary.get("warnings"))
        self._folders[str(folder)] = (key, entry)
        return entry


def no_preview(warnings) -> dict | None:
    """Why a result has no preview, as its own report's `warnings` say: {"said": one line for the preview's box,
    "why": the report's warning in full}, or None where they do not say. A warning of the preview's own ("no
    preview.png: ...", mesh_pictures.no_preview_warning), else, in a report of an earlier version (whose 3D view
    needed an off-screen OpenGL too), the 3D view's where its worker's machine could not draw off screen."""
    lines = [w for w in warnings if isinstance(w, str)] if isinstance(warnings, list) else []
    own = next((w for w in lines if w.startswith("no preview")), None)
    if own is not None:
        return {"said": WORKER_CANNOT_DRAW if OFF_SCREEN in own else own, "why": own}
    view = next((w for w in lines if w.startswith("no 3D view") and OFF_SCREEN in w), None)
    return None if view is None else {"said": WORKER_CANNOT_DRAW, "why": view}


def _mtime_ns(path: Path) -> int:
    """When `path` last changed (ns), 0 when it cannot be read: the version in its address."""
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return 0


def warning_level(warning) -> str:
    """'serious' for a warning that doubts the result's shape (SERIOUS), else 'mild'."""
    return "serious" if any(p.match(str(warning)) for p in SERIOUS) else "mild"


def serious_count(warnings) -> int:
    return sum(warning_level(w) == "serious" for w in warnings)


def final_start(report: dict | None) -> str | None:
    """Where the final run of a live job's result started, 'live' or 'hull' (its report's `live.final_start`); None
    for a result of no live job, or a report that does not say."""
    live = (report or {}).get("live")
    start = live.get("final_start") if isinstance(live, dict) else None
    return start if start in FINAL_STARTS else None


def fold_done_live(found: list[dict]) -> list[dict]:
    """`found` (the live entry first) with a live entry whose status is 'done' replaced by the result it names, when
    that result is listed: that result first, marked `from_live` (and `from_scratch` where the live job never fitted
    and reconstructed the complete scan from scratch). A done live entry whose result is not there (moved away)
    stays, without pictures (its figures are that result's)."""
    live = found[0] if found and found[0]["kind"] == LIVE else None
    result = (live or {}).get("summary", {}).get("result")
    if live is None or live["summary"].get("state") != "done" or not isinstance(result, str):
        return found
    name = Path(result).name
    own = next((f for f in found[1:] if f["id"] == name), None)
    if own is None:
        return found
    # The live job's result, but not the live fit's where its report holds no live record: its scan was complete
    # before a live fit began, and the job reconstructed it from scratch (`from_scratch`: the page says so).
    scratch = {"from_scratch": True} if own.get("live_record") is False else {}
    return [{**own, "from_live": True, **scratch}] + [f for f in found[1:] if f is not own]


def age_s(updated_utc, now: _dt.datetime) -> float | None:
    """Seconds from `updated_utc` (ISO 8601, UTC when it names no zone) to `now`, one decimal; None when unreadable."""
    then = parse_utc(updated_utc)
    return None if then is None else round(max(0.0, (now - then).total_seconds()), 1)
