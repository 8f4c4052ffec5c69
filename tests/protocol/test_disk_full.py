"""A full disk is told the one way everywhere (protocol.disk_full): ENOSPC, EDQUOT or numpy's short write, which has
no errno; found behind an error a library raised of its own; and the command line, the capture writer and a worker
job read it with that one function."""

from __future__ import annotations

import errno

import spadscan.cli as cli
import spadscan.protocol.capture_writer as capture_writer
import spadscan.worker.jobs as jobs
import spadscan.worker.report.folder_view as folder_view
from spadscan.protocol import disk_full
from spadscan.protocol.disk_full import disk_full_cause, is_disk_full, is_short_write

SHORT = "8192 requested and 3040 written"
"""numpy's short write (ndarray.tofile, np.save) on a full disk: no errno, no filename."""


def test_one_error_is_a_full_disk_or_not():
    assert is_disk_full(OSError(errno.ENOSPC, "No space left on device"))
    assert is_disk_full(OSError(errno.EDQUOT, "Disk quota exceeded"))
    assert is_disk_full(OSError(SHORT)) and is_short_write(OSError(SHORT))
    assert not is_disk_full(OSError(errno.EACCES, "Permission denied"))
    assert not is_short_write(OSError(errno.EIO, SHORT)), "a short write has no errno"
    assert not is_disk_full(OSError("something else went wrong"))
    assert not is_disk_full(ValueError(SHORT)), "only an OSError"


def test_the_full_disk_behind_an_error_is_found_along_its_causes():
    short = OSError(SHORT)
    assert disk_full_cause(short) is short
    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError as exc:
            raise RuntimeError("could not save the picture") from exc
    except RuntimeError as wrapped:
        assert disk_full_cause(wrapped).errno == errno.ENOSPC, "found behind a library's own error"
    try:
        try:
            raise OSError(errno.EDQUOT, "Disk quota exceeded")
        except OSError:
            raise OSError(errno.EIO, "closing the file")  # another write failed while handling it: its __context__
    except OSError as during:
        assert disk_full_cause(during).errno == errno.EDQUOT
    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError:
            raise TypeError("a bug in the handler")
    except TypeError as bug:
        assert disk_full_cause(bug) is None, "a bug raised while a full disk was handled is that bug"
    assert disk_full_cause(OSError(errno.EACCES, "Permission denied")) is None
    assert disk_full_cause(ValueError("bad")) is None and disk_full_cause(None) is None
    looped = ValueError("a")
    looped.__context__ = ValueError("b")
    looped.__context__.__context__ = looped
    assert disk_full_cause(looped) is None, "a loop of causes ends"


def test_the_command_line_the_capture_writer_and_the_worker_read_it_with_the_one_function():
    assert cli.is_disk_full is disk_full.is_disk_full, "the command line's name for it, kept for its callers"
    assert capture_writer.is_short_write is disk_full.is_short_write
    assert jobs.disk_full_cause is disk_full.disk_full_cause
    assert folder_view.is_disk_full is disk_full.is_disk_full
