"""Fixtures shared by the daemon's device tests."""

from __future__ import annotations

import os
import threading
import time

import pytest


@pytest.fixture
def no_leaked_threads_or_fds():
    """Fail a test that leaves a thread running or a file descriptor open (device reader threads, ports, ptys)."""
    threads, fds = set(threading.enumerate()), len(os.listdir("/proc/self/fd"))
    yield
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and set(threading.enumerate()) - threads:
        time.sleep(0.02)
    assert not set(threading.enumerate()) - threads, "test leaked threads"
    assert len(os.listdir("/proc/self/fd")) <= fds, "test leaked file descriptors"
