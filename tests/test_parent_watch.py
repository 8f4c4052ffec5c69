"""A child of `spadscan demo` stops by itself when the demo is killed outright (spadscan/parent_watch.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from spadscan.parent_watch import ENV, child_env, parent_from_env, watch_parent_from_env


def _running(pid: int) -> bool:
    """Whether `pid` is a live process (a zombie, exited but not yet reaped by its new parent, is not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return False
    return state not in ("Z", "X")


def _wait_gone(pid: int, timeout_s: float = 120.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not _running(pid):
            return True
        time.sleep(0.05)
    return False


def test_the_variable_is_taken_out_of_the_environment_for_the_grandchildren():
    env = {ENV: "12345", "OTHER": "x"}
    assert parent_from_env(env) == 12345
    assert env == {"OTHER": "x"}


def test_no_variable_or_a_malformed_one_means_no_watch():
    env = {"OTHER": "x"}
    assert watch_parent_from_env(env) is None
    assert env == {"OTHER": "x"}
    env = {ENV: "demo"}
    assert watch_parent_from_env(env) is None and env == {}


def test_child_env_names_this_process():
    assert child_env({"A": "1"}) == {"A": "1", ENV: str(os.getpid())}


def test_a_child_whose_parent_is_already_gone_stops_at_once(tmp_path):
    """The demo died while the child was starting: the child's parent (this process) is not the one named, a process
    that has already exited. (Naming a fixed pid such as 1 fails where this process is that pid: pytest as a
    container's entry point.)"""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait(timeout=60)  # exited and reaped: no process's parent
    proc = subprocess.run([sys.executable, "-m", "spadscan.cli", "worker", "--root", str(tmp_path)],
                          env={**os.environ, ENV: str(gone.pid)}, capture_output=True, text=True, timeout=120)
    assert proc.returncode in (-signal.SIGTERM, 128 + signal.SIGTERM, 0), proc.stderr


@pytest.mark.parametrize("command", [["worker", "--root", "{root}"]])
def test_the_demos_worker_stops_when_the_demo_is_killed(tmp_path, command):
    """A stand-in for the demo starts the worker through the demo's own Processes.start (its new session and its
    environment), says the worker's pid, and is then killed with SIGKILL: it can stop nothing. The worker must
    notice and leave by itself."""
    root = tmp_path / "root"
    root.mkdir()
    argv = [a.format(root=root) for a in command]
    stand_in = textwrap.dedent(f"""
        import sys, time
        from pathlib import Path
        from spadscan.demo import Processes, _spadscan
        procs = Processes()
        child = procs.start("worker", _spadscan(*{argv!r}), Path({str(tmp_path / "worker.log")!r}))
        print(child.pid, flush=True)
        log = Path({str(tmp_path / "worker.log")!r})
        while "watching" not in (log.read_text() if log.exists() else ""):
            time.sleep(0.05)
        print("ready", flush=True)
        time.sleep(3600)
    """)
    demo = subprocess.Popen([sys.executable, "-c", stand_in], stdout=subprocess.PIPE, text=True)
    worker_pid = None
    try:
        worker_pid = int(demo.stdout.readline())
        assert demo.stdout.readline().strip() == "ready", (tmp_path / "worker.log").read_text()
        assert _running(worker_pid)
        demo.send_signal(signal.SIGKILL)
        demo.wait(timeout=30)
        assert _wait_gone(worker_pid), "the worker outlived the demo that started it"
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
        if worker_pid is not None and _running(worker_pid):
            os.kill(worker_pid, signal.SIGKILL)
