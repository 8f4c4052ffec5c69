"""Fixtures shared by the daemon's device tests."""

from __future__ import annotations

import os
import threading
import time

import pytest

from spadscan.daemon import client


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


@pytest.fixture(autouse=True)
def private_socket_root(sock_dir, monkeypatch):
    """Configs read without a `socket` key make the default socket's private folder: in a short folder of the
    test's (sock_dir: under tmp_path, a long TMPDIR makes the socket's path too long), not in the machine's
    /tmp/spadscan-<uid>."""
    monkeypatch.setattr(client, "SOCKET_ROOT", str(sock_dir))
