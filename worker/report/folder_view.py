"""The 3D view of a results folder: its mesh.ply, the ground truth its report names (the part that was scored) and
the sensor poses of the capture it came from, written as view3d.html beside report.html.

Every reconstruction and baseline writes its report page through report_html, which asks for this view: so every
report has one, whoever wrote it. A view newer than its mesh is kept; one that cannot be made (a full disk) is a
warning, never a failed run: a line on stderr, and one in the report's own "warnings", so that report.json, the
worker's done line and `spadscan worker --status` say that the result has no 3D view.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from spadscan.protocol.disk_full import is_disk_full
from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.mesh_io import BUILTIN_PREFIX

from . import offscreen
from .view3d import VIEW3D, write_view3d

MESH = "mesh.ply"
GT_KEYS = ("ground_truth", "gt")
"""Report keys that name the ground-truth file it was scored against (baselines and older reports say 'gt')."""


def ground_truth_spec(report: dict, folder: Path) -> str | None:
    """The ground truth the report names, as `load_ground_truth` takes it: a built-in scene's `builtin:NAME` as it
    stands (every capture simulated from a built-in scene names one), else a file of that name in the folder first
    (a job's results name the file in the folder they were written in, before it was renamed into place), else the
    path itself."""
    for key in GT_KEYS:
        named = report.get(key)
        if not isinstance(named, str) or not named:
            continue
        if named.startswith(BUILTIN_PREFIX):
            return named
        for candidate in (folder / Path(named).name, Path(named)):
            if candidate.is_file():
                return str(candidate)
    return None


def capture_poses(capture) -> np.ndarray | None:
    """One sensor pose per scanned pose (P, 4, 4) of the capture folder `capture`, or None when it cannot be read."""
    from spadscan.protocol.capture_reader import CaptureReader

    if not isinstance(capture, str) or not capture:
        return None
    try:
        data = CaptureReader(capture).load()
    except SpadscanError:
        return None
    _, first = np.unique(data.pose_indices, return_index=True)
    return data.poses[np.sort(first)]


def ensure_view3d(report: dict, folder) -> Path | None:
    """`folder`/view3d.html for the folder's mesh.ply, made unless one newer than the mesh is there; None when the
    folder holds no mesh or the view cannot be made: a warning line says why, and `report` (the report to be
    written) gets the warning in its "warnings" (`no_view_warning`)."""
    from spadscan.protocol.mesh_io import load_mesh

    from ..ground_truth import load_ground_truth

    folder = Path(folder)
    mesh_path, path = folder / MESH, folder / VIEW3D
    if not mesh_path.is_file():
        return None
    if path.is_file() and path.stat().st_mtime_ns >= mesh_path.stat().st_mtime_ns:
        return path
    try:
        mesh = load_mesh(mesh_path, units="m")
        gt_spec = ground_truth_spec(report, folder)
        gt = load_ground_truth(gt_spec).mesh if gt_spec is not None else None
        name = Path(str(report.get("capture", folder.name))).name
        kind = report.get("preset") or report.get("method") or "reconstruction"
        return write_view3d(folder, mesh, gt, capture_poses(report.get("capture")), title=f"{name} ({kind})")
    except (SpadscanError, OSError) as exc:
        offscreen.warn(f"no {VIEW3D} in {folder}: {exc}")
        _add_warning(report, no_view_warning(exc, folder))
        return None


def no_view_warning(exc: Exception, folder=None) -> str:
    """The report's warning for a view that could not be made. An OSError's own path is left out: it names the
    folder the result was written in, which a job's result no longer is once published. A worker job's result
    (`folder` holds its job.json) that met a write error names how to get the view: the job's `redo` command, once
    there is room where the disk was full. That command only queues the job again and exits, so the warning says
    what then runs it: a worker on that root."""
    why = (exc.strerror or str(exc)) if isinstance(exc, OSError) else str(exc)
    line = f"no 3D view: {VIEW3D} could not be written ({' '.join(why.split())})"
    redo = _redo_command(folder) if isinstance(exc, OSError) else None
    if redo is None:
        return line
    first = "make room on its disk, then " if is_disk_full(exc) else ""
    return (f"{line}; {first}`{redo}` queues the job again, this result moved aside, and a worker on that root "
            f"and queue (a running one, or one started with --once) reconstructs it with its view")


def _redo_command(folder) -> str | None:
    """The command that queues again the job whose result `folder` holds (its job.json's `redo`), or None."""
    if folder is None:
        return None
    try:
        redo = json.loads((Path(folder) / "job.json").read_text()).get("redo")
    except (OSError, ValueError, AttributeError):
        return None
    return redo if isinstance(redo, str) and redo else None


def _add_warning(report: dict, warning: str) -> None:
    """Add `warning` to the report's "warnings" once (a report page written again tries the view again)."""
    own = report.get("warnings")
    own = list(own) if isinstance(own, list) else []
    if warning not in own:
        report["warnings"] = [*own, warning]
