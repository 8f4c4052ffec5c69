"""Noticing that the daemon itself was not running: SIGSTOP and SIGCONT, a debugger, a suspended laptop, a starved
machine. While the process stands still its monotonic clock goes on, so every timeout it set expires at once when it
runs again; a frame that the sensor was given seconds to deliver looks late, and the sensor gets blamed.

`StallWatch` ticks every `tick_s` on the event loop and records each gap between ticks longer than `tick_s +
threshold_s` as a stall (from the tick that should have come to the one that did). `stalled_between(t0, t1)` says
how many of those seconds fall in a window, counting a gap still open (the watch's own tick may run after the
timeout that asks). The runner asks before it calls a sensor silent, and waits again instead. Times are
`time.monotonic()` seconds.
"""

from __future__ import annotations

import asyncio
import collections
import time
from typing import Callable

TICK_S = 0.1
THRESHOLD_S = 0.5
"""A gap this much longer than a tick is a stall: a loaded machine delays a tick by far less, and a stall shorter
than this cannot make any timeout the daemon sets (seconds) fire early."""
KEEP = 64
"""Stalls remembered for `stalled_between` (the counters count all)."""


class StallWatch:
    """See the module docstring. `clock` is injectable for tests."""

    def __init__(self, tick_s: float = TICK_S, threshold_s: float = THRESHOLD_S,
                 clock: Callable[[], float] = time.monotonic):
        self.tick_s, self.threshold_s, self.clock = tick_s, threshold_s, clock
        self._last = clock()
        self._stalls: collections.deque[tuple[float, float]] = collections.deque(maxlen=KEEP)
        self.count = 0
        self.total_s = 0.0

    async def run(self) -> None:
        """Tick until cancelled."""
        self._last = self.clock()
        while True:
            await asyncio.sleep(self.tick_s)
            self.tick()

    def tick(self) -> None:
        now = self.clock()
        gap = self._open_gap(now)
        if gap is not None:
            self._stalls.append(gap)
            self.count += 1
            self.total_s += gap[1] - gap[0]
        self._last = now

    def stalled_between(self, t0: float, t1: float) -> float:
        """Seconds of [t0, t1] during which the daemon did not run (recorded stalls and one still open)."""
        spans = list(self._stalls)
        gap = self._open_gap(self.clock())
        if gap is not None:
            spans.append(gap)
        return sum(max(0.0, min(b, t1) - max(a, t0)) for a, b in spans)

    def last_stall(self) -> tuple[float, float] | None:
        """(start, end) of the latest stall (one still open ends now), or None."""
        gap = self._open_gap(self.clock())
        return gap if gap is not None else self._stalls[-1] if self._stalls else None

    def counters(self) -> dict:
        return {"count": self.count, "total_s": round(self.total_s, 3)}

    def _open_gap(self, now: float) -> tuple[float, float] | None:
        if now - self._last > self.tick_s + self.threshold_s:
            return (self._last + self.tick_s, now)
        return None
