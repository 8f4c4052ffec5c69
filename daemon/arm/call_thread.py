"""One dedicated thread that runs blocking calls in order, awaited from asyncio with a timeout.

Client libraries that are not thread-safe (ur_rtde) get every call on the same thread. A call that outlives its
timeout keeps running there (a blocking C++ call cannot be interrupted); later calls queue behind it. `overdue()`
says whether the thread is stuck in such a call, so that a caller can fail fast instead of queueing behind it, and
`abandon()` gives the stuck thread up: its queue is emptied (waiting callers get DeviceError), it ends whenever its
call returns (perhaps never: ur_rtde 1.6.5's stopL on a dead link blocks for good), and the next call starts a fresh
thread with a fresh queue.
"""

from __future__ import annotations

import asyncio
import queue
import threading
import time
from collections.abc import Callable

from spadscan.protocol.errors import DeviceError

_STOP = object()


class CallThread:
    """A worker thread for one device; `call` awaits a function run there, `stop` ends the thread."""

    def __init__(self, name: str):
        self.name = name
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._current: tuple[str, float, float] | None = None  # (what, monotonic start, timeout) of the running call

    def _run(self, q: queue.SimpleQueue) -> None:
        while (item := q.get()) is not _STOP:
            what, timeout_s, fn, args, loop, future = item
            if q is self._queue:  # an abandoned thread no longer reports what it runs
                self._current = (what, time.monotonic(), timeout_s)
            try:
                result, error = fn(*args), None
            except BaseException as exc:  # handed to the awaiting coroutine
                result, error = None, exc
            finally:
                if q is self._queue:
                    self._current = None
            if loop is not None and not loop.is_closed():
                try:
                    loop.call_soon_threadsafe(_settle, future, result, error)
                except RuntimeError:  # the loop closed meanwhile: nobody is waiting any more
                    pass

    def _ensure(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            self._thread = threading.Thread(target=self._run, args=(self._queue,), name=self.name, daemon=True)
            self._thread.start()

    async def call(self, what: str, timeout_s: float, fn: Callable, *args):
        """Run fn(*args) on the thread; raise DeviceError naming `what` when it takes longer than timeout_s."""
        self._ensure()
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        self._queue.put((what, timeout_s, fn, args, loop, future))
        try:
            # asyncio.timeout, not wait_for: in Python 3.11 wait_for can swallow a cancellation that arrives as the
            # call completes, and a cancelled move must stay cancelled.
            async with asyncio.timeout(timeout_s):
                return await future
        except TimeoutError:
            raise DeviceError(f"{self.name}: no answer within {timeout_s:g} s waiting for {what}") from None

    def post(self, fn: Callable, *args, what: str = "a posted call", timeout_s: float = 10.0) -> None:
        """Queue fn(*args) without waiting for it (errors are dropped): for last-ditch stops on cancellation.
        timeout_s: how long it may run before `overdue()` reports it."""
        self._ensure()
        self._queue.put((what, timeout_s, fn, args, None, None))

    def overdue(self) -> str | None:
        """What the thread has been running for longer than that call's timeout ('stopL for 12.3 s'), else None."""
        current = self._current
        if current is None:
            return None
        what, started, timeout_s = current
        age = time.monotonic() - started
        return f"{what} for {age:.1f} s" if age > timeout_s else None

    def abandon(self) -> None:
        """Give up the thread (see the module docstring); the next call starts a fresh one. Call from the loop."""
        q, thread = self._queue, self._thread
        self._queue, self._thread, self._current = queue.SimpleQueue(), None, None
        while True:  # calls queued behind the stuck one would run on state the caller has since replaced
            try:
                item = q.get_nowait()
            except queue.Empty:
                break
            if item is not _STOP and item[5] is not None:
                _settle(item[5], None, DeviceError(f"{self.name}: {item[0]} dropped: the arm's thread was given up"))
        if thread is not None:
            q.put(_STOP)

    async def stop(self, timeout_s: float) -> None:
        """Let queued calls finish, end the thread, wait up to timeout_s for it. Idempotent."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._queue.put(_STOP)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while thread.is_alive() and loop.time() < deadline:
            await asyncio.sleep(0.01)
        if thread.is_alive():
            raise DeviceError(f"{self.name}: worker thread still busy {timeout_s:g} s after close")


def _settle(future: asyncio.Future, result, error: BaseException | None) -> None:
    if future.done():  # the caller timed out or was cancelled
        return
    if error is not None:
        future.set_exception(error)
    else:
        future.set_result(result)
