"""A child of `spadscan demo` stops when the demo is gone.

The demo starts its simulated arm, daemon, worker and dashboard in sessions of their own, so that Ctrl-C in the
terminal reaches only the demo, which then stops them in order. A demo that is killed outright (SIGKILL, the
out-of-memory killer, a closed container) cannot stop them, and they would run on for nobody: the worker holding its
jobs, the daemon its control socket. So the demo names itself in the environment of each child, and the child watches
its parent: once the parent is no longer the demo, the child sends itself SIGTERM and leaves the way `kill PID` makes
it leave (the daemon closes its capture, the worker hands its jobs back).
"""

from __future__ import annotations

import os
import signal
import threading
import time

ENV = "SPADSCAN_EXIT_WITH_PARENT"
POLL_S = 0.5


def child_env(environ=None) -> dict[str, str]:
    """The environment for a child that should stop when this process is gone."""
    return {**(os.environ if environ is None else environ), ENV: str(os.getpid())}


def parent_from_env(environ=None) -> int | None:
    """The parent this process should stop with, taken out of the environment (ENV); None when it names none.

    Taken out, so that this process's own children (the worker's job processes) have their own parent and never
    watch this one's."""
    environ = os.environ if environ is None else environ
    value = environ.pop(ENV, None)
    try:
        return int(value) if value else None
    except ValueError:
        return None  # not ours to refuse: the command runs as it would without the variable


def watch_parent_from_env(environ=None, poll_s: float = POLL_S) -> threading.Thread | None:
    """When the environment names a parent, watch it from a daemon thread; None when it names none. A parent that is
    already gone when the watch starts (the demo died while this process was starting) ends this process at once."""
    parent = parent_from_env(environ)
    if parent is None:
        return None
    thread = threading.Thread(target=_watch, args=(parent, poll_s), name="exit-with-parent", daemon=True)
    thread.start()
    return thread


def _watch(parent: int, poll_s: float) -> None:
    # When the parent dies, the kernel gives this process a new parent (init or a subreaper): getppid() changes.
    while os.getppid() == parent:
        time.sleep(poll_s)
    os.kill(os.getpid(), signal.SIGTERM)


__all__ = ["ENV", "child_env", "parent_from_env", "watch_parent_from_env"]
