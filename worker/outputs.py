"""Result folders (`--out`) of `spadscan reconstruct` and `spadscan baseline`: never a previous result lost by
accident, never a half-written mesh left where a good one was."""

from __future__ import annotations

import os
from pathlib import Path

from spadscan.protocol.errors import ConfigError

RESULT_FILES = ("mesh.ply", "report.json")
"""Files whose presence means a folder holds a result."""


def check_out(out, overwrite: bool, capture=None) -> Path:
    """`out` as a Path, refused when it is a file, or holds a result and `overwrite` is not set, or lies inside the
    folder of `capture` (when given) anywhere but under its recon/ folder, where the worker puts results."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    if capture is not None:
        inside = _relative_to(out, Path(capture))
        if inside is not None and (not inside.parts or inside.parts[0] != "recon"):
            raise ConfigError(f"--out {out} lies inside the capture {capture}: results there would be mixed into "
                              f"its measurements; choose a folder outside it (or under its recon/ folder)")
    held = [name for name in RESULT_FILES if (out / name).exists()]
    if held and not overwrite:
        raise ConfigError(f"{out}: already holds a result ({', '.join(held)}); choose another --out, or pass "
                          "--overwrite to replace it")
    return out


def _relative_to(path: Path, folder: Path) -> Path | None:
    """`path` relative to `folder` when it lies inside it (or is it), both resolved; else None."""
    try:
        return path.resolve().relative_to(folder.resolve())
    except ValueError:
        return None


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
