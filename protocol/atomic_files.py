"""Writing a file so that a reader sees the old one or the new one, never a part: the one way every module replaces a
file (reports, statuses, pages, job outcomes, sweep records). Standard library only: the daemon-side client and the
live status use it without numpy."""

from __future__ import annotations

import os
import secrets
from pathlib import Path


def fsync_dir(path: Path) -> None:
    """Make a rename in the folder `path` durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_durable(path: Path, data: bytes) -> None:
    """Write bytes and fsync the file (the caller renames and fsyncs the folder)."""
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def write_atomic(path: Path, data: bytes | str) -> Path:
    """Replace `path` with `data` (str: UTF-8) through a hidden temporary file of this writer's own in the same
    folder (two writers of one file never share one), synced and renamed over it, the folder synced after; a failed
    write leaves the previous file and no temporary one. Returns `path`."""
    path = Path(path)
    raw = data.encode("utf-8") if isinstance(data, str) else data
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        write_durable(tmp, raw)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    fsync_dir(path.parent)
    return path


__all__ = ["fsync_dir", "write_durable", "write_atomic"]
