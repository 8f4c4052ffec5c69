"""Telling a full disk from other write errors, the one way every part of spadscan reads it.

A full disk (or a full quota) raises ENOSPC or EDQUOT, except where numpy writes an array: its short write says
"8192 requested and 3040 written" with no errno at all. What a user is told differs (the command line's one line,
a capture's chunk that names its file, a worker job that goes back to the queue), what counts as a full disk does
not.
"""

from __future__ import annotations

import errno

FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
"""The errnos of a disk (or a quota) that has no room left."""


def is_short_write(exc: BaseException) -> bool:
    """Whether `exc` is numpy's short write ("8192 requested and 3040 written"): an OSError with no errno. The
    kernel wrote less than asked, which is a full disk or a file-size limit (`ulimit -f`); where that matters, the
    caller tells which (capture_writer)."""
    if not isinstance(exc, OSError) or exc.errno is not None:
        return False
    text = str(exc)
    return "requested and" in text and "written" in text


def is_disk_full(exc: BaseException) -> bool:
    """Whether this one error is a full disk: ENOSPC, EDQUOT or numpy's short write (`is_short_write`)."""
    return isinstance(exc, OSError) and (exc.errno in FULL_ERRNOS or is_short_write(exc))


def disk_full_cause(exc: BaseException | None) -> OSError | None:
    """The full disk's error behind `exc` (`is_disk_full`), looked for along what raised it too: its __cause__ (a
    library that turns a failed write into an error of its own, `raise ... from`), and its __context__ only where it
    is itself an OSError (another write that failed while the first was handled). A bug raised while a full disk was
    being handled is that bug, not the full disk. None when it did not come of one."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if is_disk_full(exc):
            return exc
        exc = exc.__cause__ or (exc.__context__ if isinstance(exc, OSError) else None)
    return None


__all__ = ["FULL_ERRNOS", "is_short_write", "is_disk_full", "disk_full_cause"]
