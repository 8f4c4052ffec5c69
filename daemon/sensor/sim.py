"""SimSensor: the transient simulator as a `Sensor`, with the real sensor's frame timing and injectable faults.

Timing as on the TMF8820: the sensor measures back to back whether or not anyone reads. Frame k covers
[t_k, t_k + frame_time_s) with t_{k+1} = t_k + frame_time_s, starting at `prepare`. `next_frame` delivers the first
frame still in progress or yet to start: a caller that arrives mid-frame gets the frame in progress (its t_start lies
in the past, so a scan runner drops it when the arm was still moving) and a caller that keeps up gets back-to-back
frames. A frame is rendered at the pose `pose_provider()` returns when it starts (for a frame already in progress:
when the call arrives). With frame_time_s = 0 a frame starts when asked for and ends when rendered.

Rendering is this process's work, not the device's: a real sensor delivers frame k at t_k + frame_time_s however
busy our CPU is (with frame_time_s = 0, at once). The sensor's `wait_clock`, on which every frame timeout counts (its
own and the runner's frame_timeout_s), stands still from the moment a frame is due until it is handed over: a render
that a loaded machine slows, and the event loop's delay in taking it up, are never taken for a silent sensor. One
frame holds the clock still for at most `hold_max_s(timeout)` = max(HOLD_MIN_S, HOLD_TIMEOUTS x the timeout), 30 s
or ten timeouts: a render that never returns (a deadlocked library, a saturated executor) then lets the clock run
again, and the timeout raises SensorSilent, rather than a scan that waits for ever. Silences (below) pass on the clock
as on the wall.

Faults: `inject_silence(s)` (no frames for s seconds: next_frame raises SensorSilent after its timeout; the frame in
progress is lost) and `inject_link_loss(s)` (next_frame raises LinkLost at once for s seconds). Scheduled silence
(the rig config's `silence_on_frames` and `silence_s`, reachable from a daemon process): when the sensor is about to
deliver frame N (N counts the frames it delivered since it was built, from 0: over a daemon's lifetime, across
scans), it falls silent for silence_s seconds instead, once per listed N; frame N arrives after the silence.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from typing import Callable

import numpy as np

from spadscan.daemon.devices import Frame, LinkLost, Sensor, SensorSilent, wait_counted
from spadscan.protocol.errors import DeviceError
from spadscan.protocol.sensor_model import SensorModel
from spadscan.protocol.simulator import SimSettings, Simulator

HOLD_MIN_S = 30.0
"""Seconds one frame's render may hold the wait clock still at least (module docstring): a loaded machine's slow
render (seconds) stays within it."""
HOLD_TIMEOUTS = 10.0
"""And at least this many of the wait's timeouts."""


def hold_max_s(timeout_s: float, hold_min_s: float = HOLD_MIN_S) -> float:
    """The most seconds one frame may hold the wait clock of a wait of `timeout_s` seconds still."""
    return max(hold_min_s, HOLD_TIMEOUTS * timeout_s)


class SimSensor(Sensor):
    """Renders `mesh` (trimesh, metres) for `model` at the sensor pose (4, 4) from `pose_provider()`.

    `model` after construction is the simulator's effective model (settings' power, ambient and cycles folded in),
    which is what captures must store. Rendering runs in a worker thread; one frame is rendered at a time.
    """

    hold_min_s = HOLD_MIN_S
    """What `hold_max_s` allows one frame at least (a class attribute, so that a test can shorten it)."""

    def __init__(self, model: SensorModel, mesh, pose_provider: Callable[[], np.ndarray], *,
                 settings: SimSettings | None = None, seed: int = 0, frame_time_s: float = 0.0,
                 silence_on_frames: tuple[int, ...] = (), silence_s: float = 0.0):
        if not (math.isfinite(frame_time_s) and 0.0 <= frame_time_s <= 3600.0):
            raise DeviceError(f"sensor sim: frame time {frame_time_s} s is outside [0, 3600] s")
        if not (math.isfinite(silence_s) and 0.0 <= silence_s <= 3600.0):
            raise DeviceError(f"sensor sim: silence of {silence_s} s is outside [0, 3600] s")
        if any(isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0 for n in silence_on_frames):
            raise DeviceError(f"sensor sim: silence_on_frames {list(silence_on_frames)} must be frame numbers >= 0")
        if silence_on_frames and silence_s <= 0.0:
            raise DeviceError("sensor sim: silence_on_frames needs a silence_s > 0 s")
        self._sim = Simulator(mesh, model, settings if settings is not None else SimSettings(), seed)
        self.model = self._sim.sensor
        self.name = "sensor sim"
        self.pose_provider = pose_provider
        self.frame_time_s = float(frame_time_s)
        self._render_lock = threading.Lock()  # a render abandoned by a timeout may still run in its thread
        self._prev_end: float | None = None
        self._held_s = 0.0  # seconds the wait clock has stood still: frames that were due, still being produced here
        self._due: float | None = None  # when the frame being produced now is due (the clock stands still after it)
        self._hold_max_s = hold_max_s(0.0, self.hold_min_s)  # how long that frame may hold it still (next_frame's)
        self._held_too_long = False  # a frame held the clock as long as it may: said by the timeout that follows
        self._silent_until = -math.inf
        self._down_until = -math.inf
        self._silence_on = {int(n) for n in silence_on_frames}  # frame numbers still to be silenced
        self.silence_s = float(silence_s)
        self._counts = {"frames": 0, "frames_lost_to_silence": 0, "silent_timeouts": 0, "faults_injected": 0}

    # ---- lifecycle -----------------------------------------------------------------------------------------------
    async def prepare(self) -> None:
        if self._prev_end is None:
            self._prev_end = time.monotonic()  # the stream of back-to-back frames starts now

    async def release(self) -> None:
        self._prev_end = None

    # ---- faults --------------------------------------------------------------------------------------------------
    def inject_silence(self, duration_s: float) -> None:
        """No frames for duration_s seconds from now; the frame in progress is lost."""
        self._silent_until = max(self._silent_until, time.monotonic() + duration_s)
        self._counts["faults_injected"] += 1

    def inject_link_loss(self, duration_s: float) -> None:
        """next_frame raises LinkLost for duration_s seconds from now."""
        self._down_until = max(self._down_until, time.monotonic() + duration_s)
        self._counts["faults_injected"] += 1

    def end_link_loss(self) -> None:
        """An injected link loss ends now: the link is back (a cable plugged in again)."""
        self._down_until = -math.inf

    # ---- frames --------------------------------------------------------------------------------------------------
    async def next_frame(self, timeout_s: float) -> Frame:
        if self._prev_end is None:
            raise DeviceError(f"{self.name}: next_frame before prepare (the sensor is not streaming)")
        self._hold_max_s, self._held_too_long = hold_max_s(timeout_s, self.hold_min_s), False
        try:
            return await wait_counted(self._next(), timeout_s, self.wait_clock)
        except TimeoutError:
            self._counts["silent_timeouts"] += 1
            why = (f"a frame's render here held the wait for {self._hold_max_s:g} s, the most one frame may"
                   if self._held_too_long else "")
            raise SensorSilent(f"{self.name}: no complete frame within {timeout_s:g} s" + (f" ({why})" if why else ""),
                               detail=why) from None  # (the runner words the timeout and keeps the detail)

    def wait_clock(self) -> float:
        """time.monotonic() less the time frames were due from the device but still being produced here, each frame
        at most `hold_max_s` of its wait's timeout (see the module docstring)."""
        now = time.monotonic()
        return now - self._held_s - self._holding(now)

    def _holding(self, now: float) -> float:
        """Seconds the frame being produced holds the wait clock still at `now` (0: none is due yet)."""
        if self._due is None:
            return 0.0
        held = max(0.0, now - self._due)
        if held >= self._hold_max_s:
            self._held_too_long = True
        return min(held, self._hold_max_s)

    def counters(self) -> dict:
        out = dict(self._counts)
        now = time.monotonic()
        out["silent"] = now < self._silent_until
        out["link"] = "down" if now < self._down_until else "up"
        out["late_render_s"] = round(self._held_s, 3)  # frames due but still rendering: this process's delay
        return out

    async def _next(self) -> Frame:
        while True:
            now = time.monotonic()
            if now < self._down_until:
                raise LinkLost(f"{self.name}: link down for another {self._down_until - now:.1f} s (injected)")
            if self._counts["frames"] in self._silence_on:  # scheduled: this frame is due, the sensor goes quiet
                self._silence_on.discard(self._counts["frames"])
                self.inject_silence(self.silence_s)
            start = self._frame_start(now)
            await _sleep_until(start)
            pose = np.asarray(self.pose_provider(), dtype=np.float64)
            # When the device delivers it: from then on the wait is this process's delay. (Not earlier than now: the
            # clock never steps back; an event loop late to begin the render is late for every timer alike.)
            self._due = max(start + self.frame_time_s, time.monotonic())
            try:
                frames = await asyncio.to_thread(self._render, pose)
                end = max(self._due, time.monotonic())
                await _sleep_until(end)
            finally:
                self._handed_over()
            self._prev_end = end
            if self._silent_until > start:  # silenced while this frame was exposed: it never arrives
                self._counts["frames_lost_to_silence"] += 1
                continue
            self._counts["frames"] += 1
            return Frame(hists=frames.hists[0], t_start=start, t_end=end,
                         reference=None if frames.reference is None else frames.reference[0],
                         extra={"render_pose": pose.tolist()})

    def _handed_over(self) -> None:
        """The frame being produced is handed over (or lost, or its wait cancelled): the wait clock runs again."""
        self._held_s += self._holding(time.monotonic())
        self._due = None

    def _frame_start(self, now: float) -> float:
        """Start of the first frame that has not ended by `now` (monotonic seconds), after any silence."""
        start = self._prev_end
        if self.frame_time_s == 0.0:
            start = max(start, now)
        elif now > start:
            start += math.floor((now - start) / self.frame_time_s) * self.frame_time_s
        if start < self._silent_until:  # frames resume when the silence ends
            start = self._silent_until
        return start

    def _render(self, pose: np.ndarray):
        with self._render_lock:
            return self._sim.frames(pose[None])


async def _sleep_until(t: float) -> None:
    delay = t - time.monotonic()
    if delay > 0:
        await asyncio.sleep(delay)
