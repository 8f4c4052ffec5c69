"""One dedicated thread that runs blocking calls in order, awaited from asyncio with a timeout.

Client libraries that are not thread-safe (ur_rtde) get every call on the same thread. A call that outlives its
timeout keeps running there (a blocking C++ call cannot be interrupted); later calls queue behind it.
"""

from __future__ import annotations

import asyncio
import queue
import threading
from collections.abc import Callable

from spadscan.protocol.errors import DeviceError

_STOP = object()


class CallThread:
    """A worker thread for one device; `call` awaits a function run there, `stop` ends the thread."""

    def __init__(self, name: str):
        self.name = name
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._thread: threading.Thread | None = None

    def _run(self) -> None:
        while (item := self._queue.get()) is not _STOP:
            fn, args, loop, future = item
            try:
                result, error = fn(*args), None
            except BaseException as exc:  # handed to the awaiting coroutine
                result, error = None, exc
            if loop is not None and not loop.is_closed():
                try:
                    loop.call_soon_threadsafe(_settle, future, result, error)
                except RuntimeError:  # the loop closed meanwhile: nobody is waiting any more
                    pass

    def _ensure(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
            self._thread.start()

    async def call(self, what: str, timeout_s: float, fn: Callable, *args):
        """Run fn(*args) on the thread; raise DeviceError naming `what` when it takes longer than timeout_s."""
        self._ensure()
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        self._queue.put((fn, args, loop, future))
        try:
            # asyncio.timeout, not wait_for: in Python 3.11 wait_for can swallow a cancellation that arrives as the
            # call completes, and a cancelled move must stay cancelled.
            async with asyncio.timeout(timeout_s):
                return await future
        except TimeoutError:
            raise DeviceError(f"{self.name}: no answer within {timeout_s:g} s waiting for {what}") from None

    def post(self, fn: Callable, *args) -> None:
        """Queue fn(*args) without waiting for it (errors are dropped): for last-ditch stops on cancellation."""
        self._ensure()
        self._queue.put((fn, args, None, None))

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
