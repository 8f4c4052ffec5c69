"""Result folders (`--out`) of `spadscan reconstruct` and `spadscan baseline`: never a previous result lost by
accident, never a half-written mesh left where a good one was."""

from __future__ import annotations

import os
from pathlib import Path

from spadscan.protocol.errors import ConfigError

RESULT_FILES = ("mesh.ply", "report.json")
"""Files whose presence means a folder holds a result."""


def check_out(out, overwrite: bool) -> Path:
    """`out` as a Path, refused when it is a file, or holds a result and `overwrite` is not set."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    held = [name for name in RESULT_FILES if (out / name).exists()]
    if held and not overwrite:
        raise ConfigError(f"{out}: already holds a result ({', '.join(held)}); choose another --out, or pass "
                          "--overwrite to replace it")
    return out


def export_mesh(mesh, path, **options) -> Path:
    """Write `mesh` as PLY to `path` through a temporary file renamed over it: a failed write (a full disk) leaves
    the previous file, not a truncated one. `options` go to trimesh's export (e.g. vertex_normal=True)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        mesh.export(tmp, file_type="ply", **options)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def capture_state_note(capture, state: str, views: int) -> str | None:
    """A warning for a capture that is not complete (a scan still running, paused or aborted), or None."""
    if state == "complete":
        return None
    return (f"{capture}: the capture is {state}, not complete: reconstructing the {views} views it holds so far")


__all__ = ["RESULT_FILES", "check_out", "export_mesh", "capture_state_note"]
