"""Processes a test starts are stopped by it, however it ends."""

from __future__ import annotations

import contextlib
import subprocess


@contextlib.contextmanager
def reaped(*procs: subprocess.Popen):
    """Yield `procs`; on the way out (a failed assertion, a timeout), kill each one still running and reap it, so
    that no process of a failed test goes on loading the machine for the tests after it."""
    try:
        yield procs
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
            with contextlib.suppress(subprocess.TimeoutExpired, OSError, ValueError):
                proc.communicate(timeout=30)
