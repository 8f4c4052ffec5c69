"""Signals for the commands that write one folder from start to end (simulate, import-lcspc) and the dashboard."""

from __future__ import annotations

import contextlib
import signal
import threading


@contextlib.contextmanager
def terminate_as_interrupt():
    """Within the block, SIGTERM (`kill`, a service stop, a time limit) ends the command as Ctrl-C does: the command's
    clean-up runs and the capture's manifest says it was interrupted. Python's default for SIGTERM is to die on the
    spot, which left a half-written capture saying 'running', as if still being written.

    Only the main thread can set a handler; elsewhere (a test calling a command from a thread) the block runs as is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
