"""The device interfaces the scan runner drives, and the plain data they return.

Every device follows one lifecycle: connect -> prepare -> (act) -> release -> close. Concrete backends live in
`daemon/arm/` (ur, sim) and `daemon/sensor/` (serial, i2c, sim); the runner sees only these classes. Times are
`time.monotonic()` seconds of the daemon process (frame timeouts count on a sensor's `wait_clock`, with
`wait_counted`); poses are 4x4 float64 in metres.
"""

from __future__ import annotations

import abc
import asyncio
import time
from dataclasses import dataclass, field
from typing import Awaitable, Callable, TypeVar

import numpy as np

from spadscan.protocol.errors import DeviceError
from spadscan.protocol.sensor_model import SensorModel

T = TypeVar("T")


class ArmFault(DeviceError):
    """The arm refused or aborted a motion: protective stop, emergency stop, workspace violation."""


class LinkLost(DeviceError):
    """A device's link dropped (stale data, closed port, unplugged cable)."""


class SensorSilent(DeviceError):
    """The sensor delivered no frame within its timeout. `detail`: why, where the sensor knows (the error its bridge
    reported), or ''; the runner words the timeout itself and keeps this part."""

    def __init__(self, message: str, detail: str = ""):
        super().__init__(message)
        self.detail = detail


class FramesTooEarly(DeviceError):
    """The sensor delivered frames, but every one began before the arm had settled (a backlog that does not drain)."""


@dataclass
class ArmState:
    """What the arm reports: actual TCP pose (4x4, base frame, metres), joint angles (rad), controller time (s), and
    whether a safety stop holds it: `safety_stop` names which (`arm/stops.py`: emergency, protective, safeguard stop),
    for an arm that can tell; `protective_stop` says only that one does (it follows `safety_stop`)."""

    tcp_pose: np.ndarray
    joints: np.ndarray
    timestamp_s: float
    protective_stop: bool = False
    safety_stop: str | None = None

    def __post_init__(self) -> None:
        if self.safety_stop is not None:
            self.protective_stop = True


@dataclass
class Frame:
    """One sensor frame. hists (zones, bins) uint32 counts; reference (bins,) uint32 or None.

    t_start / t_end: monotonic seconds when the frame's exposure began (at the earliest: never later than the true
    start, so that the runner can drop frames exposed while the arm moved) / when it was received.
    """

    hists: np.ndarray
    t_start: float
    t_end: float
    reference: np.ndarray | None = None
    temperature_c: float | None = None
    depths_mm: list[float] | None = None
    confidences: list[int] | None = None
    extra: dict = field(default_factory=dict)


class Device(abc.ABC):
    """Lifecycle shared by every device. Implementations make each step idempotent."""

    name: str = "device"

    async def connect(self) -> None:
        """Open the link (socket, serial port, bus)."""

    async def prepare(self) -> None:
        """Bring the device to a ready state (boot, configure, power the arm)."""

    async def release(self) -> None:
        """Leave the device safe (stop motion, stop measuring). Always called, also after errors."""

    async def close(self) -> None:
        """Close the link."""


class Arm(Device):
    """A robot arm that carries the sensor on its tool flange."""

    name = "arm"

    @abc.abstractmethod
    async def move_to(self, tcp_pose: np.ndarray, speed: float, accel: float) -> None:
        """Move linearly to a TCP pose (4x4, metres) at speed (m/s) and acceleration (m/s^2); returns once stopped.

        Raises ArmFault when the controller refuses or aborts the move, LinkLost when the link is gone.
        """

    @abc.abstractmethod
    async def state(self) -> ArmState:
        """The actual (measured) state. Raises LinkLost when the data is stale."""

    @abc.abstractmethod
    async def stop(self) -> None:
        """Stop any motion now."""

    async def reconnect(self) -> None:
        """Open the link afresh after LinkLost; the runner calls it when a scan resumes after a lost link. Raises
        LinkLost while the link is still down. Default: `connect()` (idempotent)."""
        await self.connect()

    async def clear_fault(self) -> None:
        """Called when the user resumes a scan that an ArmFault paused. The operator clears a real arm's safety stop
        on the teach pendant before resuming; the UR arm uploads its control script again if a fault stopped it; a
        simulated arm clears its stop."""

    async def read_speed_slider(self) -> None:
        """Read the speed slider of an arm whose controller has one (the pendant's: `speed_slider`, a fraction, and
        `speed_slider_at`, the time.monotonic() of the controller's latest report of it) now, as nothing else does
        while no move runs (a paused scan). One read, nothing else: no move, no stop, no check of the link. Default:
        an arm without a slider, nothing to read."""

    async def check_poses(self, tcp_poses: np.ndarray, first_index: int = 0) -> None:
        """Ask the arm's controller whether it can reach every TCP pose (P, 4, 4, numbered from first_index) within
        its own safety limits; ArmFault naming the first it refuses. Default: a controller with nothing to ask."""


class Sensor(Device):
    """A time-of-flight sensor that streams histogram frames."""

    name = "sensor"
    model: SensorModel

    @abc.abstractmethod
    async def next_frame(self, timeout_s: float) -> Frame:
        """The next complete frame. Raises SensorSilent after timeout_s seconds without one."""

    def wait_clock(self) -> float:
        """The clock (seconds) that frame timeouts count on: `next_frame`'s own and the runner's frame_timeout_s.
        A real sensor's frames come on the device's own timing, whatever this process is doing: time.monotonic(). A
        simulated sensor's frames are produced by this process (`sensor/sim.py` renders them on a thread): its clock
        stands still while a frame the device would already have delivered is still being produced here, so that a
        loaded machine is not taken for a silent sensor. It never runs faster than time.monotonic()."""
        return time.monotonic()

    def starting_left(self) -> float:
        """Seconds (on `wait_clock`) the sensor may still take to deliver its first frame after a start it began on
        its own (a serial bridge that reset and set its sensor up again after a replug); 0 when none is under way. A
        frame wait that runs out sooner is begun again, not taken for a silent sensor. Default: 0."""
        return 0.0

    async def begin_exposure(self) -> float | None:
        """Called once the arm has settled at a pose: a sensor that can start a fresh exposure (stop and restart its
        measurement) does so and returns the monotonic time from which every later frame's exposure lies; None when
        it cannot (it keeps measuring on its own clock). Either way each frame's `t_start` must be a lower bound on
        when its exposure began: the runner drops frames whose `t_start` is before the arm settled."""
        return None

    def counters(self) -> dict:
        """Health counters (frames, corrupt lines skipped, reconnects, ...), for `ctl status`."""
        return {}


async def wait_counted(aw: Awaitable[T], timeout_s: float, clock: Callable[[], float]) -> T:
    """Await `aw` for at most timeout_s seconds counted on `clock` (a sensor's `wait_clock`): asyncio.wait_for, except
    that time during which the clock stands still does not count. TimeoutError once they have passed, `aw` then
    cancelled (and so when the caller is cancelled). `clock` never runs faster than time.monotonic(), so a wait of
    the seconds still left on it never sleeps past the deadline."""
    task = asyncio.ensure_future(aw)
    end = clock() + timeout_s
    try:
        while not task.done():
            left = end - clock()
            if left <= 0:
                raise TimeoutError
            await asyncio.wait((task,), timeout=left)
        return task.result()
    finally:
        if not task.done():
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
