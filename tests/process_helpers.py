"""Processes a test starts are stopped by it, however it ends."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from pathlib import Path


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


def live_children() -> set[int]:
    """Live child processes of this process (from /proc), zombies excluded."""
    pids: set[int] = set()
    for task in Path(f"/proc/{os.getpid()}/task").iterdir():
        try:
            pids.update(int(p) for p in (task / "children").read_text().split())
        except OSError:
            continue
    live = set()
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            live.add(pid)
    return live


def stop_leaked_children(before: set[int], grace_s: float = 30.0) -> set[int]:
    """Child processes alive now that were not in `before`, once they have had `grace_s` to exit: on a loaded
    machine a stopping process (an interpreter unwinding, a child reaping its own) can take seconds to be scheduled.
    Those still alive are killed (SIGKILL): a leaked process must not outlive the test run. Returns them."""
    leaked = live_children() - before
    deadline = time.monotonic() + grace_s
    while leaked and time.monotonic() < deadline:
        time.sleep(0.05)
        leaked = live_children() - before
    for pid in leaked:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return leaked
