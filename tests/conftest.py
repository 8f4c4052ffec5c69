"""Shared fixtures: every test must stop the processes and asyncio tasks it starts."""

from __future__ import annotations

import asyncio
import shutil
import signal
from pathlib import Path

import pytest

from benchmark_helpers import load_benchmark
from process_helpers import live_children, short_socket_dir, stop_leaked_children
from spadscan import parent_watch
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.worker import cpu_wait, kill_points, threads

DATASET = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "lcspc"


def pytest_configure(config):
    """Ctrl-C reaches the commands the tests start, however the suite was started.

    A run started in the background (`bash tests/run.sh &`, nohup, many CI runners) inherits SIGINT ignored, every
    process it starts inherits that, and Python leaves an ignored SIGINT ignored: a test that interrupts a command
    then waits for an exit that never comes. A handler (unlike an ignored signal) is reset to the default by exec,
    so installing Python's own here gives every child the default again."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="module")
def bench():
    """benchmarks/error_vs_time.py loaded as a module (a script, not part of the package)."""
    return load_benchmark("error_vs_time")


@pytest.fixture(autouse=True)
def no_leaked_processes():
    """Fail a test that leaves a child process running (and stop that process)."""
    before = live_children()
    yield
    leaked = stop_leaked_children(before)
    assert not leaked, f"test leaked child processes {sorted(leaked)} (killed)"


PRODUCT_ENV = ("SPADSCAN_SOCKET", parent_watch.ENV, kill_points.ENV, threads.ADAPT_ENV, cpu_wait.MACHINE_JOBS_ENV)
"""The product's own variables, none of them the tests' to inherit: the user's SPADSCAN_SOCKET (exported for a
daemon of theirs) sends a test's daemon or ctl to that socket; a SPADSCAN_EXIT_WITH_PARENT of a demo's child makes a
command watch a parent that is not the test's; SPADSCAN_KILL_AT kills a worker at a step; SPADSCAN_ADAPT_THREADS
changes how a job's threads are chosen; SPADSCAN_MACHINE_JOBS (a worker's job, run by hand) changes what a busy
warning says. A test that needs one sets it itself."""


@pytest.fixture(autouse=True)
def no_product_env(monkeypatch):
    """Every test, and every command it starts, runs without the user's PRODUCT_ENV (put back after the test)."""
    for name in PRODUCT_ENV:
        monkeypatch.delenv(name, raising=False)


@pytest.fixture
def sock_dir():
    """A fresh short folder for the test's Unix sockets (see process_helpers.short_socket_dir), removed after it.
    For a test whose point is not the socket's path: one under tmp_path fails where TMPDIR is long."""
    folder = short_socket_dir()
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def arun():
    """Run a coroutine in a fresh event loop and fail if it leaves tasks behind."""

    def run(coro, timeout_s: float = 120.0):
        async def wrapper():
            result = await asyncio.wait_for(coro, timeout_s)
            await asyncio.sleep(0)
            others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task() and not t.done()]
            assert not others, f"coroutine leaked asyncio tasks: {others}"
            return result

        return asyncio.run(wrapper())

    return run


@pytest.fixture
def lcspc_dataset() -> Path:
    """The public dataset folder; skips the test (saying why) when it is not there."""
    if not DATASET.is_dir():
        pytest.skip(f"LCSPCData not found at {DATASET}")
    return DATASET


@pytest.fixture
def reads(monkeypatch):
    """The names of the chunks of a capture read whole (CaptureReader.read_chunk), in order: what a resume reads."""
    names: list[str] = []
    real = CaptureReader.read_chunk

    def read_chunk(self, name):
        names.append(name)
        return real(self, name)

    monkeypatch.setattr(CaptureReader, "read_chunk", read_chunk)
    return names
