"""Whether a folder a command must make can be made, asked before anything runs: `--out`, `--queue`, a rig's
`captures`. Standard library only (the light CLI and the daemon's config check use it).

os.access cannot answer it: root may write anywhere by its rules, yet not into /proc, a read-only mount or an
immutable folder. So a missing folder is tried for real: a scratch folder is made, and removed, where the first mkdir
would go.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .errors import ConfigError


def file_in_the_way(path) -> str | None:
    """The first existing component of `path` that is not a folder (the reason for ENOTDIR), or None."""
    for parent in reversed(Path(path).parents):
        if str(parent) not in ("", ".") and parent.exists() and not parent.is_dir():
            return str(parent)
    p = Path(path)
    return str(p) if p.exists() and not p.is_dir() else None


def not_a_folder(path) -> str | None:
    """Why `path` can never be a folder, or None: it is a file (or another non-folder), or a file stands where one
    of the folders above it would go. Reads only."""
    path = Path(path)
    if os.path.lexists(path) and not path.is_dir():
        return "a file, not a folder" if path.is_file() else "not a folder"
    blocker = file_in_the_way(path)
    return None if blocker is None else f"{blocker} is a file, not a folder"


def folder_problem(path) -> str | None:
    """Why the folder `path` is not there and cannot be made, or None; one that can be made is left unmade."""
    path = Path(path)
    reason = not_a_folder(path)
    if reason is not None or path.is_dir():
        return reason
    above = next(parent for parent in path.absolute().parents if parent.is_dir())
    try:
        scratch = tempfile.mkdtemp(prefix=".spadscan-check-", dir=above)
    except OSError as exc:
        return f"cannot create it ({exc.strerror or exc})"
    os.rmdir(scratch)  # outside the try: a scratch folder that stays is an error of its own, not "cannot create"
    return None


def check_folder_option(path, option: str) -> None:
    """Refuse, in one line that names the option or key (`--out`, `captures`), a folder that is not there and
    cannot be made."""
    reason = folder_problem(path)
    if reason is not None:
        raise ConfigError(f"{option} {path}: {reason}")


__all__ = ["file_in_the_way", "not_a_folder", "folder_problem", "check_folder_option"]
