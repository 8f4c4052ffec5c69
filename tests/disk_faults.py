"""Disk faults for tests of capture reading: a file this user may not open, a file whose lookup fails."""

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
