"""A simulated arm: linear moves that take time, an actual pose that follows the commanded one, injectable faults.

Motion time follows a trapezoidal speed profile from the move's distance, speed and acceleration (or a fixed time;
0 = instant), scaled by `time_scale`. While a move runs the actual pose slides along the straight line, so a sensor
that renders at the arm's pose sees motion. Faults rehearse what a real UR does: a safety stop (protective, safeguard
or emergency: `stops`) half way through a chosen move, or at any moment (`trigger_stop`: also while the arm stands at
a pose); the move raises ArmFault, the state names the stop, and every later move is refused until the stop is
cleared. Or a link drop: state and moves raise LinkLost, and go on raising it after `restore_link` until the arm
reconnects (`reconnect`, as the runner does on resume), as a real arm's dropped connection does. An injected fault
freezes the arm at exactly `interpolate_pose(start, goal, 0.5)`, whatever the clock says. Joint angles are a fake but
deterministic function of the pose.

Clearing a safety stop: on a real UR the operator clears it (the pendant, the emergency stop button, the safeguard),
then resumes the scan. The sim has no pendant, so `clear_fault()` (which the scan runner calls when the user resumes
a scan an arm fault paused, `spadscan ctl resume`) clears it, as does `clear_safety_stop()`.
"""

from __future__ import annotations

import asyncio
import math
import time
from dataclasses import dataclass

import numpy as np

from spadscan.daemon.arm.pose_convert import matrix_to_rotvec, rotvec_to_matrix
from spadscan.daemon.arm.stops import EMERGENCY_STOP, PROTECTIVE_STOP, SAFEGUARD_STOP, clear_advice
from spadscan.daemon.devices import Arm, ArmFault, ArmState, LinkLost
from spadscan.protocol.errors import ConfigError

# Home: 0.6 m above the base origin, tool z pointing down.
HOME = np.array([[1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, 0.6], [0, 0, 0, 1]])


@dataclass(frozen=True)
class SimArmFaults:
    """Faults to inject, by move number (1 = the first move_to call)."""

    protective_stop_on_moves: tuple[int, ...] = ()
    """Moves that stop protectively half way."""
    safeguard_stop_on_moves: tuple[int, ...] = ()
    """Moves that a safeguard stop (a light curtain, a door) halts half way."""
    emergency_stop_on_moves: tuple[int, ...] = ()
    """Moves that an emergency stop halts half way."""
    link_drop_on_moves: tuple[int, ...] = ()
    """Moves during which the link drops (the move raises LinkLost half way)."""


def interpolate_pose(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    """The pose a fraction s in [0, 1] of the way from a to b (straight line, rotation about one axis)."""
    out = np.eye(4)
    out[:3, 3] = (1 - s) * a[:3, 3] + s * b[:3, 3]
    out[:3, :3] = a[:3, :3] @ rotvec_to_matrix(s * matrix_to_rotvec(a[:3, :3].T @ b[:3, :3]))
    return out


def trapezoid_time(distance_m: float, speed: float, accel: float) -> float:
    """Seconds to travel distance_m from rest to rest at most `speed` (m/s) with acceleration `accel` (m/s^2)."""
    if distance_m <= 0:
        return 0.0
    if distance_m > speed * speed / accel:
        return distance_m / speed + speed / accel
    return 2 * math.sqrt(distance_m / accel)


def fake_joints(pose: np.ndarray) -> np.ndarray:
    """Six plausible joint angles (rad) that change smoothly with the TCP pose; not a real inverse kinematics."""
    x, y, z = pose[:3, 3]
    rv = matrix_to_rotvec(pose[:3, :3])
    return np.array([math.atan2(y, x), -math.atan2(z, math.hypot(x, y)), math.hypot(x, y, z) - 0.5, *rv])


class SimArm(Arm):
    """Simulated arm. motion_time_s None: trapezoidal timing at min(move speed, `speed`) m/s; a number: fixed."""

    def __init__(self, *, motion_time_s: float | None = None, speed: float = 0.25, time_scale: float = 1.0,
                 faults: SimArmFaults = SimArmFaults(), pose_noise_m: float = 0.0, seed: int = 0,
                 home: np.ndarray | None = None):
        if motion_time_s is not None and not (_number(motion_time_s) and motion_time_s >= 0):
            raise ConfigError(f"sim arm motion_time_s = {motion_time_s!r} must be a finite number >= 0 (s)")
        for label, value, ok in (("speed", speed, "> 0 (m/s)"), ("time_scale", time_scale, ">= 0"),
                                 ("pose_noise_m", pose_noise_m, ">= 0 (m)")):
            if not (_number(value) and (value > 0 if label == "speed" else value >= 0)):
                raise ConfigError(f"sim arm {label} = {value!r} must be a finite number {ok}")
        if home is not None and np.shape(home) != (4, 4):
            raise ConfigError(f"sim arm home must be a 4x4 pose, got shape {np.shape(home)}")
        self.name = "arm (sim)"
        self.motion_time_s = motion_time_s
        self.max_speed = float(speed)
        self.time_scale = float(time_scale)
        self.faults = faults
        self.pose_noise_m = float(pose_noise_m)
        self._rng = np.random.default_rng(seed)
        self._pose = np.array(HOME if home is None else home, dtype=float)
        self._motion: tuple[np.ndarray, np.ndarray, float, float] | None = None  # start, goal, t0, duration
        self._ended: asyncio.Event | None = None  # set when the move in progress is stopped
        self.moves = 0
        self.commanded: list[np.ndarray] = []
        self.safety_stop: str | None = None
        """The safety stop that holds the arm (`stops`), None when none does."""
        self.link_up = True
        self._link_dropped = False  # the link dropped since the last (re)connect: LinkLost until the next
        self.connected = False

    # ---- lifecycle ---------------------------------------------------------------------------------------------
    async def connect(self) -> None:
        await self.reconnect()

    @property
    def protective_stop(self) -> bool:
        """Stopped for safety, whichever stop (ArmState.protective_stop)."""
        return self.safety_stop is not None

    async def close(self) -> None:
        self.connected = False

    async def release(self) -> None:
        await self.stop()

    # ---- faults ------------------------------------------------------------------------------------------------
    def trigger_stop(self, kind: str = PROTECTIVE_STOP) -> None:
        """Stop for safety now: PROTECTIVE_STOP (as a collision would), SAFEGUARD_STOP (a light curtain, a door) or
        EMERGENCY_STOP (the red button). The move in progress raises ArmFault; at rest, the state names the stop."""
        if kind not in (EMERGENCY_STOP, PROTECTIVE_STOP, SAFEGUARD_STOP):
            raise ValueError(f"unknown safety stop {kind!r}")
        self._freeze()
        self.safety_stop = kind

    def trigger_protective_stop(self) -> None:
        """Stop protectively now (as a collision would); the move in progress raises ArmFault."""
        self.trigger_stop(PROTECTIVE_STOP)

    def clear_safety_stop(self) -> None:
        """What the operator does on the teach pendant (or at the button, the safeguard) after a safety stop."""
        self.safety_stop = None

    def clear_protective_stop(self) -> None:
        self.clear_safety_stop()

    async def clear_fault(self) -> None:
        """The user resumed after an arm fault: clear the safety stop (the sim's stand-in for the pendant)."""
        self.clear_safety_stop()

    async def reconnect(self) -> None:
        """LinkLost while the link is still down (see `restore_link`); otherwise connected again."""
        if not self.link_up:
            raise LinkLost(f"{self.name}: link lost (no fresh state data)")
        self._link_dropped = False
        self.connected = True

    def drop_link(self) -> None:
        self._freeze()
        self.link_up = self.connected = False
        self._link_dropped = True

    def restore_link(self) -> None:
        """The link is back (a cable plugged in again, a controller rebooted); the arm reconnects before using it."""
        self.link_up = True

    def jog(self, tcp_pose: np.ndarray) -> None:
        """Put the arm at a TCP pose (4, 4) at once, as an operator does with the teach pendant's jog buttons while
        a scan is paused."""
        self._motion = None
        self._pose = np.array(tcp_pose, dtype=float)

    # ---- motion ------------------------------------------------------------------------------------------------
    def actual_pose(self) -> np.ndarray:
        """The actual TCP pose (4, 4) now, also mid-move (thread-safe: reads one snapshot of the motion)."""
        motion = self._motion
        if motion is None:
            return self._pose.copy()
        start, goal, t0, duration = motion
        s = 1.0 if duration <= 0 else min(1.0, max(0.0, (time.monotonic() - t0) / duration))
        return interpolate_pose(start, goal, s)

    def motion_time(self, start: np.ndarray, goal: np.ndarray, speed: float, accel: float) -> float:
        if self.motion_time_s is not None:
            return self.motion_time_s * self.time_scale
        distance = float(np.linalg.norm(goal[:3, 3] - start[:3, 3]))
        return trapezoid_time(distance, min(speed, self.max_speed), accel) * self.time_scale

    async def move_to(self, tcp_pose: np.ndarray, speed: float, accel: float) -> None:
        goal = np.array(tcp_pose, dtype=float)
        if goal.shape != (4, 4) or not np.all(np.isfinite(goal)):
            raise ArmFault(f"{self.name}: target pose must be a finite 4x4 array, got shape {goal.shape}")
        if not (speed > 0 and accel > 0):
            raise ArmFault(f"{self.name}: speed {speed} m/s and acceleration {accel} m/s^2 must be positive")
        self._check_link()
        if self.safety_stop is not None:
            raise ArmFault(f"{self.name}: {self.safety_stop}; {clear_advice(self.safety_stop)}")
        self.moves += 1
        self.commanded.append(goal.copy())
        start = self.actual_pose()
        duration = self.motion_time(start, goal, speed, accel)
        fault = self._fault_on(self.moves)
        motion = (start, goal, time.monotonic(), duration)
        self._motion = motion
        # A stop, a protective stop or a dropped link ends the move at once, as on a real controller (its moveL
        # returns when stopped), instead of after the time the whole move would have taken.
        self._ended = ended = asyncio.Event()
        try:
            try:
                await asyncio.wait_for(ended.wait(), duration / 2 if fault else duration)
            except asyncio.TimeoutError:
                pass
            if fault and self._motion is motion:  # half way, exactly: not wherever the clock has got to
                self._pose, self._motion = interpolate_pose(start, goal, 0.5), None
            if fault == "link":
                self.drop_link()
            elif fault is not None:
                self.safety_stop = fault
            self._check_link()
            if self.safety_stop is not None:
                raise ArmFault(f"{self.name}: {self.safety_stop} during move {self.moves}; "
                               f"{clear_advice(self.safety_stop)}")
            if self._motion is not motion:
                raise ArmFault(f"{self.name}: move {self.moves} was stopped before it arrived")
            self._motion = None
            self._pose = self._noisy(goal)
        finally:
            if self._motion is motion:
                self._freeze()

    def _fault_on(self, move: int) -> str | None:
        """The fault injected into move number `move`: a safety stop's name, "link", or None."""
        f = self.faults
        for kind, moves in ((PROTECTIVE_STOP, f.protective_stop_on_moves), (SAFEGUARD_STOP, f.safeguard_stop_on_moves),
                            (EMERGENCY_STOP, f.emergency_stop_on_moves), ("link", f.link_drop_on_moves)):
            if move in moves:
                return kind
        return None

    def _noisy(self, goal: np.ndarray) -> np.ndarray:
        if self.pose_noise_m <= 0:
            return goal.copy()
        out = goal.copy()
        out[:3, 3] += self._rng.normal(0.0, self.pose_noise_m, 3)
        return out

    def _freeze(self) -> None:
        """End any motion where the arm is now."""
        if self._motion is not None:
            self._pose = self.actual_pose()
            self._motion = None
            if self._ended is not None:
                self._ended.set()

    def _check_link(self) -> None:
        if not self.link_up:
            raise LinkLost(f"{self.name}: link lost (no fresh state data)")
        if self._link_dropped:
            raise LinkLost(f"{self.name}: the link dropped and the connection is closed; reconnect first")

    async def state(self) -> ArmState:
        self._check_link()
        pose = self.actual_pose()
        return ArmState(tcp_pose=pose, joints=fake_joints(pose), timestamp_s=time.monotonic(),
                         safety_stop=self.safety_stop)

    async def stop(self) -> None:
        self._freeze()


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
