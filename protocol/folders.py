"""Whether a folder a command must write into can be written into, or made, asked before anything runs: `--out`,
`--queue`, a rig's `captures`. Standard library only (the light CLI and the daemon's config check use it).

os.access cannot answer it: it says yes to root for /proc and /sys, where the real mkdir says no (a file system's own
rules are not the permission bits it reads). So it is tried for real: a scratch folder is made, and removed, in the
folder when it is there, and where the first mkdir would go when it is not.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .errors import ConfigError


def file_in_the_way(path) -> str | None:
    """The first component of `path`, from the top, that is there and is not a folder (a file, or a link to
    nothing), or None: the reason for ENOTDIR, and what keeps a folder from being made there."""
    path = Path(path)
    for part in [*reversed(path.parents), path]:
        if str(part) not in ("", ".") and os.path.lexists(part) and not part.is_dir():
            return str(part)
    return None


def not_a_folder(path) -> str | None:
    """Why `path` can never be a folder, or None: it is a file (or another non-folder, or a link to nothing), or such
    a thing stands where one of the folders above it would go. Reads only."""
    found = file_in_the_way(path)
    if found is None:
        return None
    part = Path(found)
    what = "a link to a missing folder" if part.is_symlink() and not part.exists() else (
        "a file, not a folder" if part.is_file() else "not a folder")
    return what if part == Path(path) else f"{part} is {what}"


def folder_problem(path, writable: bool = True) -> str | None:
    """Why the folder `path` cannot be written into (it is there) or made (it is not), in words that follow the path,
    or None; tried by a scratch folder made and removed in it, or in the nearest folder above it that is there, so
    that one that can be made is left unmade. With `writable` false a folder that is there passes untried: for a
    command that only reads one that is there (`worker --status`), yet would have it made when it is not."""
    path = Path(path)
    there = False
    try:
        reason = not_a_folder(path)
        there = reason is None and path.is_dir()
        if reason is not None or (there and not writable):
            return reason
        above = path if there else next(parent for parent in path.absolute().parents if parent.is_dir())
        scratch = tempfile.mkdtemp(prefix=".spadscan-check-", dir=above)
    except OSError as exc:  # /proc, a read-only mount, an immutable folder, one above that this user may not search
        return f"{'cannot write into it' if there else 'cannot create it'} ({exc.strerror or exc})"
    os.rmdir(scratch)  # outside the try: a scratch folder that stays is an error of its own, not "cannot create"
    return None


def check_folder_option(path, option: str) -> None:
    """Refuse, in one line that names the option or key (`--out`, `captures`) and the user's path, a folder that
    cannot be written into or made (`folder_problem`)."""
    reason = folder_problem(path)
    if reason is not None:
        raise ConfigError(f"{option} {path}: {reason}")


__all__ = ["file_in_the_way", "not_a_folder", "folder_problem", "check_folder_option"]
