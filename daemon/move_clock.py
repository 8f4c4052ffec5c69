"""A move's time limit counted in motion time, at the pace of the arm's speed slider: a move the teach pendant
slows is not taken for a stuck one."""

from __future__ import annotations

import asyncio

from .describe import SLIDER_FLOOR, SLIDER_FULL

MOVE_TICK_S = 0.05  # how often a move's time limit is set again from the arm's speed slider (`MoveClock.follow`)


class MoveClock:
    """A move's time limit (`limit_s`, move_timeout_s) counted in motion time: wall time at the pace of the arm's
    speed slider as the arm last read it (`slider`: a fraction, None for an arm without one: full pace), so that
    at 5 % a second counts 0.05 s; never slower than SLIDER_FLOOR. A UR arm reads its slider at every poll of a
    move, so the pace follows the pendant within a poll; the limit is set again every MOVE_TICK_S (`follow`)."""

    def __init__(self, limit_s: float, slider):
        self.limit_s, self._slider = float(limit_s), slider
        self._loop = asyncio.get_running_loop()
        self.begun = self._last = self._loop.time()
        self.spent = 0.0  # motion time (s) counted up to self._last
        self.pace = self.slowest = self._read()

    def _read(self) -> float:
        slider = self._slider()
        return 1.0 if slider is None else min(1.0, max(SLIDER_FLOOR, float(slider)))

    def deadline(self) -> float:
        """When the limit runs out at the pace read now (the event loop's clock). The time since the last call
        counts at the slower of the paces read then and now: a move slowed meanwhile is never cut short."""
        now, pace = self._loop.time(), self._read()
        self.spent += (now - self._last) * min(pace, self.pace)
        self._last, self.pace, self.slowest = now, pace, min(self.slowest, pace)
        return now + max(0.0, self.limit_s - self.spent) / pace

    async def follow(self, limit: asyncio.Timeout) -> None:
        """Set `limit` (the move's asyncio timeout) again every MOVE_TICK_S, until it expires."""
        while True:
            await asyncio.sleep(MOVE_TICK_S)
            if limit.expired():
                return
            limit.reschedule(self.deadline())

    def timed_out(self, arm: str, i: int) -> str:
        """Why the move to pose i was stopped, with what to do: one that the speed slider slowed names it."""
        said = f"{arm}: move to pose {i} did not finish within {self.limit_s:g} s (move_timeout_s)"
        if self.slowest < SLIDER_FULL:
            now = self._read()
            slider = (f"at {now * 100:.3g} %" if now < SLIDER_FULL else
                      f"down to {self.slowest * 100:.3g} % during the move")
            said += (f" of motion, counted at the pace of the pendant's speed slider ({slider}; "
                     f"{self._loop.time() - self.begun:.1f} s in all)")
        return f"{said}; see on the teach pendant what holds the arm up, then `spadscan ctl resume`"
