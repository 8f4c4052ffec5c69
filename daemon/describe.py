"""One line for the operator about what went wrong in the daemon: a write error (a full disk named as such), a device
fault, or our own error's message; and what slows it (an arm's speed slider)."""

from __future__ import annotations

import errno

from spadscan.protocol.errors import SpadscanError

from .devices import ArmFault, LinkLost, SensorSilent


def describe(exc: BaseException, doing: str = "publishing") -> str:
    """`exc` said in one line; `doing`: what the daemon was doing when an OSError struck ("while <doing>")."""
    if isinstance(exc, OSError):
        what = "disk full" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else "write error"
        where = f" ({exc.filename})" if exc.filename else ""
        return f"{what} while {doing}: {exc.strerror or exc}{where}"
    if isinstance(exc, SensorSilent):
        return f"sensor silent: {exc}"
    if isinstance(exc, ArmFault):
        return f"arm fault: {exc}"
    if isinstance(exc, LinkLost):
        return f"link lost: {exc}"
    return str(exc) if isinstance(exc, SpadscanError) else f"{type(exc).__name__}: {exc}"


SLIDER_FULL = 0.995
"""An arm's speed slider at or above this reads as 100 % (a controller reports a float)."""


def slider_note(fraction: float) -> str:
    """What a robot controller's speed slider below 100 % means, for the operator (a scan crawls, and says why)."""
    return f"the controller runs moves at {fraction * 100:.3g} % (the pendant's speed slider)"
