"""Processes a test starts are stopped by it, however it ends."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest


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


def short_socket_dir() -> Path:
    """A fresh folder (mode 0700) with a short path, for Unix sockets: a socket's path has at most 107 bytes, and
    tmp_path, under a long TMPDIR, can be longer. In /tmp, not $TMPDIR, for that reason; its user removes it."""
    return Path(tempfile.mkdtemp(prefix="ss-", dir="/tmp"))


def permissions_apply() -> list[str]:
    """The command prefix under which a process started by root is refused what a file's mode refuses (an ordinary
    user needs none): root keeps its identity and drops its capability to override permissions. Becoming another user
    instead would also lose what root alone may read (the interpreter's library in a root-only home, a .pth file that
    pip, run by root under umask 077, wrote 0600). Skips the test, saying why, where root cannot drop it."""
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("running as root without setpriv: permissions cannot apply")
    # From the bounding set, and from the inheritable and ambient sets too: a root process that holds the
    # capabilities there (older Docker gives them so) would get them back across exec.
    caps = "-dac_override,-dac_read_search"
    prefix = [setpriv, f"--bounding-set={caps}", f"--inh-caps={caps}", f"--ambient-caps={caps}"]
    problem = _modes_problem(prefix)
    if problem is not None:
        pytest.skip(f"running as root where permissions cannot apply: {problem}")
    return prefix


# Exits 13 (EACCES) when the file given is refused to it, 0 when it opened it.
_OPEN_PROBE = "import sys\ntry:\n    open(sys.argv[1]).close()\nexcept PermissionError:\n    sys.exit(13)"


def _modes_problem(prefix: list[str]) -> str | None:
    """None when a process started under `prefix` is refused a file of mode 000, as file modes refuse it to an
    ordinary user; else why not, in words. Tried for real: that setpriv ran is no proof of what its process may do."""
    with tempfile.TemporaryDirectory(prefix="modes-") as folder:
        shut = Path(folder) / "shut"
        shut.write_text("")
        shut.chmod(0o000)
        probe = subprocess.run(prefix + [sys.executable, "-c", _OPEN_PROBE, str(shut)], capture_output=True,
                               text=True, timeout=120)
    if probe.returncode == 13:
        return None
    if probe.returncode == 0:
        return "a process under setpriv still opened a file of mode 000 (it keeps a capability to override modes)"
    said = probe.stderr.strip().splitlines() or [f"exit {probe.returncode}"]
    return f"setpriv could not drop the capability to override modes ({said[-1]})"
