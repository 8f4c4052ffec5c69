"""The reconstructions of a scan as the dashboard lists them: each finished job's results folder
(`<scan>/recon/<job>/`, its report.json summed up, links to report.html, preview.png and view3d.html) and the live
one while a scan is reconstructed as it runs (`<scan>/recon/live/`: status.json, preview.png, mesh.ply).

Folders are remembered by their modification times, like the scans (scans.py).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from .paths import safe_path, url_path

RECON = "recon"
LIVE = "live"
SUMMARY_KEYS = ("preset", "method", "chamfer_mm", "accuracy_mm", "completeness_mm", "fscore_5mm", "steps",
                "seconds", "stopped_by", "converged", "warnings", "capture_state", "ground_truth_note")
LIVE_KEYS = ("views_used", "views_published", "steps", "updated_utc", "converged", "chamfer_mm")
PAGES = ("report.html", "preview.png", "view3d.html", "error_vs_time.png", "coverage.png", "mesh.ply")


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

    def for_scan(self, scan: str) -> list[dict]:
        """The scan's reconstructions: the live one first, then finished ones, newest first. Each: id, kind
        ('live' or 'final'), files (URL paths under /files/ of those present), summary or status, error."""
        recon = self.root / scan / RECON
        try:
            names = [e.name for e in os.scandir(recon) if e.is_dir() and not e.name.startswith(".")
                     and ".replaced-" not in e.name]
        except OSError:
            return []
        found = [self._folder(scan, recon / name) for name in names]
        found = [f for f in found if f is not None]
        found.sort(key=lambda f: (f["kind"] != LIVE, -f["mtime"]))
        return found

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
        if not isinstance(summary.get("warnings", []), list):
            # the page lists them one a line: anything else would stop its whole refresh, every scan with it
            error = f"{main.name}: warnings {json.dumps(summary.pop('warnings'))[:40]} is not a list"
        # a link only to what the server serves (safe_path): never one to a folder linked out of the root
        files = {p: f"/files/{rel}?v={st.st_mtime_ns}"
                 for p in PAGES if safe_path(self.root, rel := url_path(scan, RECON, folder.name, p))}
        if live and "mesh.ply" in files:  # the server makes the live view from that very mesh
            files["view3d.html"] = f"/live3d/{url_path(scan)}?v={st.st_mtime_ns}"
        entry = {"id": folder.name, "scan": scan, "kind": LIVE if live else "final", "mtime": st.st_mtime,
                 "summary": summary, "error": error, "files": files}
        self._folders[str(folder)] = (key, entry)
        return entry
