"""Shared fixtures: every test must stop the processes and asyncio tasks it starts."""

from __future__ import annotations

import asyncio
import signal
from pathlib import Path

import pytest

from benchmark_helpers import load_benchmark
from process_helpers import live_children, stop_leaked_children

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
