"""One line for the operator about what went wrong in the daemon: a write error (a full disk named as such, a file
larger than the daemon's file-size limit and too many open files told apart from it), a device fault, or our own
error's message; what to do about a write error (`write_advice`); and what slows a move (an arm's speed slider)."""

from __future__ import annotations

import errno
import os
import resource

from spadscan.protocol.capture_writer import file_size_limit
from spadscan.protocol.disk_full import FULL_ERRNOS
from spadscan.protocol.errors import SpadscanError

from .devices import ArmFault, LinkLost, SensorSilent

NOT_WRITABLE = (errno.EROFS, errno.EACCES, errno.EPERM)
"""The errnos of a captures' folder the daemon may not write (a disk remounted read-only, permissions)."""


def describe(exc: BaseException, doing: str = "publishing") -> str:
    """`exc` said in one line; `doing`: what the daemon was doing when an OSError struck ("while <doing>")."""
    if isinstance(exc, OSError):
        where = f" ({exc.filename})" if exc.filename else ""
        if exc.errno == errno.EFBIG:  # not a full disk: the process may not write a file that large (ulimit -f)
            limit = file_size_limit()
            said = f"; the daemon may write files of at most {limit} bytes (ulimit -f)" if limit is not None else ""
            return f"file too large while {doing}: {exc.strerror or exc}{where}{said}"
        if exc.errno == errno.EMFILE:  # not the disk: this process holds as many files as it may (ulimit -n)
            limit = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
            return (f"too many open files while {doing}: {exc.strerror or exc}{where}; the daemon may hold "
                    f"{limit} open at once (ulimit -n)")
        if exc.errno == errno.ENFILE:
            return f"too many open files on this machine while {doing}: {exc.strerror or exc}{where}"
        what = "disk full" if exc.errno in FULL_ERRNOS else "write error"
        return f"{what} while {doing}: {exc.strerror or exc}{where}"
    if isinstance(exc, SensorSilent):
        return f"sensor silent: {exc}"
    if isinstance(exc, ArmFault):
        return f"arm fault: {exc}"
    if isinstance(exc, LinkLost):
        return f"link lost: {exc}"
    return str(exc) if isinstance(exc, SpadscanError) else f"{type(exc).__name__}: {exc}"


def write_advice(exc: OSError) -> str:
    """What the operator does about write error `exc` before `spadscan ctl resume`, as a clause ending in it."""
    if exc.errno in FULL_ERRNOS:
        fix = "make room on the captures' disk"
    elif exc.errno == errno.EFBIG:
        fix = _raise_file_size_limit()
    elif exc.errno in NOT_WRITABLE:
        fix = "make the captures' folder writable"
    elif exc.errno == errno.EMFILE:
        fix = _raise_open_file_limit()
    elif exc.errno == errno.ENFILE:
        fix = "close programs that hold many files open (the machine's limit is `sysctl fs.file-max`)"
    else:
        fix = "check the captures' disk (the kernel log names a failing one)"
    return f"{fix}, then `spadscan ctl resume`"


def _raise_file_size_limit() -> str:
    """How the operator raises this process's file-size limit: `prlimit` on the running daemon while its hard limit
    allows more (no restart: the paused scan goes on), else only a daemon started with a higher one can (`ulimit -f`
    sets both limits; raising a hard limit takes privileges)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    if soft != resource.RLIM_INFINITY and (hard == resource.RLIM_INFINITY or hard > soft):
        to = "unlimited" if hard == resource.RLIM_INFINITY else str(hard)
        return f"raise the daemon's file-size limit (`prlimit --pid {os.getpid()} --fsize={to}`)"
    return ("start the daemon again with a higher file-size limit (`ulimit -f` where it is started, systemd's "
            "LimitFSIZE=)")


def _raise_open_file_limit() -> str:
    """How the operator frees or raises this process's open files: what holds them (a script's connections left
    open) goes first; `prlimit` raises the limit of the running daemon while its hard limit allows more."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    to = "unlimited" if hard == resource.RLIM_INFINITY else str(hard)
    raise_it = (f"raise the daemon's open-file limit (`prlimit --pid {os.getpid()} --nofile={to}`)"
                if hard == resource.RLIM_INFINITY or hard > soft else
                "start the daemon again with a higher open-file limit (`ulimit -n`, systemd's LimitNOFILE=)")
    return f"close what holds connections to the daemon open (a script's, a stuck program's) or {raise_it}"


SLIDER_FULL = 0.995
"""An arm's speed slider at or above this reads as 100 % (a controller reports a float)."""
SLIDER_FLOOR = 0.01
"""The slowest pace a move's time limit is counted at (a slider at 0 % would stretch it without end)."""


def slider_note(fraction: float, age_s: float | None = None) -> str:
    """What a robot controller's speed slider below 100 % means, for the operator (a scan crawls, and says why);
    `age_s`: how long ago it was read, said where given (a reading that could not be renewed)."""
    read = f", as read {age_s:.0f} s ago" if age_s is not None else ""
    return f"the controller runs moves at {fraction * 100:.3g} % (the pendant's speed slider{read})"
