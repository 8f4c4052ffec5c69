"""Disk faults for tests: a file this user may not open, a file whose lookup fails, a disk that fills up."""

from __future__ import annotations

import builtins
import errno
import os
from pathlib import Path

from spadscan.protocol import capture_format


def deny_open(monkeypatch, denied: Path) -> None:
    """Make read_npy's open of `denied` fail as a file of another user's with mode 600 would (EACCES; as root, chmod
    would not)."""
    def guarded_open(file, *args, **kwargs):
        if os.fspath(file) == os.fspath(denied):
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(file))
        return builtins.open(file, *args, **kwargs)

    monkeypatch.setattr(capture_format, "open", guarded_open, raising=False)


def fail_lookup(monkeypatch, failing: Path) -> None:
    """Make looking `failing` up fail with EIO, as a failing disk's stat does (the folder's listing and its other
    files still read)."""
    exists = Path.exists

    def guarded_exists(self, *args, **kwargs):
        if os.fspath(self) == os.fspath(failing):
            raise OSError(errno.EIO, "Input/output error", os.fspath(self))
        return exists(self, *args, **kwargs)

    monkeypatch.setattr(Path, "exists", guarded_exists)


def switchable_full_disk(monkeypatch, module, name: str) -> dict:
    """Replace `module.name`, a writer called as (path, data), by one that raises ENOSPC naming the path while the
    returned switch's "on" is true, as a full disk would, and writes as before while it is false (it starts so)."""
    real = getattr(module, name)
    full = {"on": False}

    def write(path, data):
        if full["on"]:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real(path, data)

    monkeypatch.setattr(module, name, write)
    return full
