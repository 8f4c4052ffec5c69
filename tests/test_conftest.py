"""The suite's own set-up: Ctrl-C reaches the commands the tests start, also when the suite was started with SIGINT
ignored (in the background, under nohup, by a CI runner)."""

from __future__ import annotations

import importlib.util
import signal
import subprocess
import sys
from pathlib import Path

# By its path: `import conftest` finds whichever folder's conftest pytest loaded first.
_spec = importlib.util.spec_from_file_location("suite_conftest", Path(__file__).with_name("conftest.py"))
conftest = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(conftest)

CHILD = "import signal; print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)"


def test_an_ignored_sigint_is_restored_for_the_commands_tests_start():
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a background run inherits it
    try:
        ignored = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60)
        assert ignored.stdout.strip() == "False"  # a child of an ignoring parent ignores Ctrl-C: the problem
        conftest.pytest_configure(None)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        child = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60)
        assert child.stdout.strip() == "True", child.stderr
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_handler_the_run_installed_is_left_alone():
    def mine(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, mine)
    try:
        conftest.pytest_configure(None)
        assert signal.getsignal(signal.SIGINT) is mine
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_leaked_child_process_is_reported_and_stopped():
    import subprocess

    from process_helpers import live_children, stop_leaked_children

    before = live_children()
    child = subprocess.Popen(["sleep", "300"])
    assert stop_leaked_children(before, grace_s=0.1) == {child.pid}
    assert child.wait(timeout=30) == -9, "killed, not left running after the tests"
