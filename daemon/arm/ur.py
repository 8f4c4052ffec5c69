"""URArm: a Universal Robots arm through the real ur_rtde client (RTDEControlInterface + RTDEReceiveInterface).

The ur_rtde client runs in a child process (`RTDELink`, `rtde_child.py`): ur_rtde 1.6.5 can crash the process that
holds it when a dropped link comes back, and a crash there is a lost link here, never a dead daemon. Every call is
awaited with a timeout whose error names the arm and what it waited for. Moves are sent asynchronously (moveL with
asynchronous=True) and then polled, so that a stop, a fault or a dead link is seen while the arm travels.

What ur_rtde does not tell by raising, this class checks:
- a move refused or aborted returns False (or the async move just ends): protective and emergency stops are read
  from the safety status and raised as ArmFault;
- after a link drop the receive getters keep returning the last values: the controller timestamp must advance, and
  one stuck for `stale_after_s` raises LinkLost;
- after a move, the actual pose must reach the target (within `position_tol_m` / `rotation_tol_rad`) and the
  actual TCP speed fall below `rest_speed` / `rest_angular_speed`: the receive stream may lag the control stream,
  so "move finished" alone does not mean the reading shows the arm at rest.
- safety stops: protective (safety_status_bits bit 2), emergency (bit 7) and safeguard (bit 4, safety mode 5 or 12:
  a light curtain or a door) all raise ArmFault; so do a safety violation and a safety fault (safety mode 8 or 9,
  bit 8 or 9: the safety system itself stopped the arm, and the controller the program), whose advice differs: UR
  requires the arm's safety system to be restarted from the pendant, not a stop unlocked. A control script that is
  no longer running (a protective or emergency stop pauses it, the watchdog stops it, so may the pendant)
  raises ArmFault too, naming the safety mode, and `clear_fault()` (the runner calls it when the scan resumes)
  uploads it again (reuploadScript; a fresh connection if that fails) unless a violation or fault still holds the
  arm (no program runs until the arm is restarted: the next move names it again);
- the speed slider: a move's time budget counts time at the controller's combined speed scaling, so a slowed arm
  is not taken for a stuck one (the runner's move_timeout_s counts at the slider's pace too, `speed_slider`: read
  at every poll of a move, and by `read_speed_slider` for a status while no move runs);
- the active TCP: spadscan's poses are the tool flange's (sensor pose = TCP pose x [arm] hand_eye), so the
  controller's active TCP offset (getTCPOffset) must be zero, within TCP_OFFSET_TOL_M / TCP_OFFSET_TOL_RAD. It is
  read at connect (unless a safety stop keeps the script from answering) and, for every program ur_rtde starts
  (connect, reupload), at the latest before the first pose check or move; a non-zero one (a "pointer" TCP left
  active after measuring a calibration target) raises ArmFault naming it. PolyScope before 3.6 cannot tell
  (`rtde_child.TCP_OFFSET_SINCE`) and is not asked.
The controller's watchdog (setWatchdog, right after every connection - in the ur_rtde process, as the control
interface is constructed - or script upload; at the first prepare or move where a safety stop kept the script from
taking it) stops the program, and with it the arm, when no input arrives for 1/watchdog_hz s: the daemon's event loop
kicks it (kickWatchdog) three times per period from connect to close, so an arm whose daemon went silent (killed,
stopped, hung) stops by itself. An orderly close (`close`, also after a failed `prepare`) first ends the control
script (stopScript: ur_rtde's disconnect() leaves it running on the controller, until the watchdog stops it or, with
none armed, for good); where the script cannot take that command (a safety stop holds it) or the link is dead, the
watchdog stops it, as it does when the ur_rtde process is killed. `check_poses` asks the controller
itself about every planned pose (isPoseWithinSafetyLimits, and getInverseKinematicsHasSolution where its PolyScope
answers it: 5.10 on, 3.15 on a CB-series arm).
Any LinkLost ends the client process (a closed link's interfaces would otherwise go on reconnecting by themselves,
which is what crashes ur_rtde), after one stopL that may take at most STOP_ON_LOSS_S (a link found stale may still
carry it; the move it can no longer watch then stops), and every later call fails at once with LinkLost until
`connect()` or `reconnect()` starts a fresh process with new interfaces (ur_rtde's own `reconnect()` can crash the
process too). A dead link can wedge a control call for good (ur_rtde 1.6.5's stopL on a dropped link never returns),
so `stop()` reads the link first and raises LinkLost instead of calling stopL on a dead link, and a call that
outlives its timeout ends the process. Keeping ur_rtde out of the daemon's process also keeps its GIL traps out of
the event loop (its constructors hold the GIL while they connect, its destructors for ~0.5 s each).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from spadscan.daemon.arm.rtde_link import RTDELink
from spadscan.daemon.arm.pose_convert import pose_to_vector, rotation_angle, rotvec_to_matrix, vector_to_pose
# The safety modes and status bits stay importable from this module too.
from spadscan.daemon.arm.safety_hold import (BIT_FAULT, BIT_SAFEGUARD_STOPPED, BIT_VIOLATION,  # noqa: F401
                                             MODE_FAULT, MODE_VIOLATION, ROBOT_MODE_RUNNING, SAFEGUARD_MODES,
                                             SAFETY_MODES, holding_stop, not_ready, safety_fault)
from spadscan.daemon.arm.stops import clear_advice
from spadscan.daemon.describe import SLIDER_FLOOR, SLIDER_FULL, slider_note
from spadscan.daemon.devices import Arm, ArmFault, ArmState, LinkLost
from spadscan.protocol.errors import ConfigError, DeviceError

log = logging.getLogger("spadscan.daemon")

MAX_TOOL_SPEED = 3.0
"""m/s: ur_rtde rejects faster moveL speeds."""
MAX_TOOL_ACCEL = 150.0
"""m/s^2: ur_rtde rejects larger moveL accelerations."""
STOP_DECEL = 10.0
"""m/s^2: tool deceleration of stop() (ur_rtde's stopL default)."""
START_GRACE_S = 2.0
"""Longest wait (s) for an asynchronous move to report itself running before "not running" is taken as its end:
its thread starts within a controller cycle; this also covers a slow link and a busy machine."""
STOP_ON_LOSS_S = 1.0
"""s: how long the stopL sent before a lost link is dropped may take."""
CLEARED_WITHIN_S = 2.0
"""s: on resume, how long a safety stop the operator has just cleared may still show in the data before it counts."""
SAFETY_CATCH_UP_S = 0.5
"""s: how long a control script seen stopped is read again for the safety stop that may have stopped it (the
receive stream can lag the control stream)."""
TCP_OFFSET_TOL_M = 1e-4
"""m: largest translation of the controller's active TCP offset still taken for the bare flange."""
TCP_OFFSET_TOL_RAD = 1e-3
"""rad: largest rotation of the controller's active TCP offset still taken for the bare flange."""
MIN_SPEED_SCALING = SLIDER_FLOOR
"""A move's time budget runs at the speed scaling, but never slower than this (a slider at zero would stretch it
without end), as the runner's move_timeout_s does."""


@dataclass(frozen=True)
class _Reading:
    """One consistent read of the receive interface (taken in the ur_rtde process)."""

    pose_vec: np.ndarray  # (6,) [m, rad]
    joints: np.ndarray  # (6,) rad
    timestamp: float  # controller seconds
    protective: bool
    emergency: bool
    safety_mode: int
    connected: bool
    tcp_speed: np.ndarray  # (6,) linear m/s, angular rad/s
    moving: bool = False  # an asynchronous move is still running (control interface)
    safety_bits: int = 0  # safety_status_bits
    program_running: bool = True  # the control script runs (commands can be taken)
    speed_scaling: float = 1.0  # combined: speed slider x trajectory scaling
    op_id: int = -1  # the last asynchronous move that started (progress readings only; -1 otherwise)
    paused: bool = False  # the program is paused (runtime state PAUSING/PAUSED: a protective or emergency stop)
    robot_mode: int = ROBOT_MODE_RUNNING  # UR's robot mode: 7 running, 3 powered off, 5 its brakes on (`not_ready`)

    @property
    def safety_fault(self) -> str | None:
        """SAFETY_FAULT or SAFETY_VIOLATION when the safety system itself stopped the arm, else None."""
        return safety_fault(self.safety_mode, self.safety_bits)

    @property
    def stop(self) -> str | None:
        """The safety stop that holds the arm (`stops`), None when none does: `safety_hold.holding_stop`, the
        predicate the ur_rtde process uses too."""
        return holding_stop(self.protective, self.emergency, self.safety_mode, self.safety_bits)


class URArm(Arm):
    """A UR arm over ur_rtde; see the module docstring. Speeds in m/s, accelerations in m/s^2, times in s."""

    def __init__(self, host: str, *, speed: float = 0.1, accel: float = 0.3, timeout_s: float = 10.0,
                 stale_after_s: float = 0.5, frequency: float | None = None, position_tol_m: float = 1e-3,
                 rotation_tol_rad: float = 0.01, rest_speed: float = 2e-3, rest_angular_speed: float = 0.02,
                 poll_s: float = 0.005, watchdog_hz: float = 2.0):
        if not isinstance(host, str) or not host:
            raise ConfigError(f"UR arm host must be a non-empty string, got {host!r}")
        for label, value, hi in (("speed", speed, MAX_TOOL_SPEED), ("accel", accel, MAX_TOOL_ACCEL),
                                 ("timeout_s", timeout_s, 3600.0), ("stale_after_s", stale_after_s, 60.0),
                                 ("position_tol_m", position_tol_m, 0.1), ("rotation_tol_rad", rotation_tol_rad, 1.0),
                                 ("rest_speed", rest_speed, 1.0), ("rest_angular_speed", rest_angular_speed, 1.0),
                                 ("poll_s", poll_s, 1.0), ("frequency", 1.0 if frequency is None else frequency, 500.0),
                                 ("watchdog_hz", watchdog_hz, 100.0)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and 0 < value <= hi):
                raise ConfigError(f"UR arm {label} must be in (0, {hi:g}], got {value!r}")
        self.host, self.speed, self.accel = host, float(speed), float(accel)
        self.timeout_s, self.stale_after_s = float(timeout_s), float(stale_after_s)
        self.frequency = -1.0 if frequency is None else float(frequency)  # -1: ur_rtde's default (500 Hz on e-series)
        self.position_tol_m, self.rotation_tol_rad, self.poll_s = position_tol_m, rotation_tol_rad, poll_s
        self.rest_speed, self.rest_angular_speed = rest_speed, rest_angular_speed
        self.watchdog_hz = float(watchdog_hz)
        self.name = f"UR arm {host}"
        self._link: RTDELink | None = None  # the ur_rtde client process, once connected
        self._kicker: asyncio.Task | None = None  # kicks the controller's watchdog while the link is open
        self._watchdog_set = False  # setWatchdog taken by the script now running
        self._tcp_checked = False  # the script now running reported a zero TCP offset (or cannot tell)
        self.tcp_offset: list[float] | None = None
        """The active TCP offset (pose vector [m, rad], flange frame) last read from the controller; None before the
        first read, or where the controller cannot tell."""
        self.speed_slider: float | None = None
        """The pendant's speed slider (target speed fraction, 0..1) last read from the controller; None before the
        first read. `ctl status` shows it when below 1: a slowed arm otherwise looks like a slow or stuck scan."""
        self.speed_slider_at: float | None = None
        """When (time.monotonic()) a reading fresh from the controller (its timestamp advanced) last carried
        `speed_slider`: a link gone stale repeats the last values, which say nothing of the slider now."""
        self._slider_ts: float | None = None  # the controller timestamp of that reading
        # The last controller timestamp seen and when it last changed.
        self._last_ts: float | None = None
        self._last_change = 0.0
        self._open = False

    # -- lifecycle ---------------------------------------------------------------------------------------------
    async def connect(self) -> None:
        """Open both interfaces (uploads ur_rtde's control script) and wait for live data. Idempotent; after a lost
        link it reconnects."""
        if self._open:
            try:
                await self._fresh("live data")
                return
            except LinkLost:
                pass
        await self.reconnect()

    async def reconnect(self) -> None:
        """Drop the interfaces and build new ones, in a fresh ur_rtde process."""
        await self._close_link()
        self._link = RTDELink(self.name)
        wait_s = self.timeout_s + 15.0
        # A controller that does not answer holds the start-up for wait_s: say so before it starts.
        log.info("connecting to %s (up to %g s)", self.name, wait_s)
        try:
            await self._link.start()
            opened = await self._call(f"connection to {self.host}", "open", self.host, self.frequency,
                                      self.watchdog_hz, timeout_s=wait_s)
        except BaseException as exc:
            self._link.end(f"connecting failed: {exc}")  # no client process is left behind a failed connect
            await self._close_link()
            if isinstance(exc, OSError):
                raise DeviceError(f"{self.name}: cannot start the ur_rtde process: {exc}") from None
            raise
        self._open = True
        self._last_ts = None
        # The ur_rtde process armed the watchdog as it connected (unless a safety stop held the script: then prepare
        # or the first move does). Arming it before prepare is safe only because the kicks start here, with the link,
        # and go on until it is closed: through prepare, between scans, while a scan is paused. Nothing else writes
        # to the controller while the daemon waits, and without them the watchdog would stop the script then.
        self._watchdog_set, self._tcp_checked = bool(opened["watchdog"]), False
        self._kicker = asyncio.ensure_future(self._kick_watchdog())
        reading = await self._fresh("the first data after connecting")
        if reading.program_running and reading.stop is None:
            await self._check_tcp_offset()  # else before the first move: a stopped arm's script answers nothing

    async def prepare(self) -> None:
        """Refuse to start while the arm is stopped for safety, its control script is not running or its active TCP
        is not the bare flange; arm the watchdog."""
        reading = await self._fresh("the safety state")
        await self._raise_if_stopped(reading, "cannot prepare")
        await self._check_tcp_offset()
        await self._arm_watchdog()

    async def clear_fault(self) -> None:
        """The scan resumes after an arm fault (the operator has cleared any safety stop on the pendant). A control
        script that stopped meanwhile is uploaded again (reuploadScript; a fresh connection if it does not start)
        and the watchdog armed again (and its TCP offset read again: a new program takes the installation's TCP); a
        safety stop still active is left to the next move to report."""
        self._require_open()
        reading = await self._fresh("the control script's state")
        deadline = time.monotonic() + CLEARED_WITHIN_S
        while reading.stop is not None and time.monotonic() < deadline:
            await asyncio.sleep(self.poll_s)  # a stop cleared just now may still show in the data already sent
            reading = await self._fresh("the control script's state")
        if not reading.program_running and reading.safety_fault is None:  # no program runs until a restart
            unpowered = not_ready(reading.robot_mode)
            if unpowered is not None:  # its script would not start: ur_rtde's connection would give up on it
                raise ArmFault(f"{self.name}: {unpowered}")
            await self._call("reuploadScript", "reupload")
            if await self._script_started():
                self._watchdog_set = self._tcp_checked = False  # a new program: it has no watchdog yet
            else:
                await self.reconnect()  # its ur_rtde process armed the new program's watchdog: keep what it set
        if reading.stop is None:
            await self._check_tcp_offset()
            await self._arm_watchdog()

    async def _script_started(self) -> bool:
        """Whether a fresh reading shows the control script running within timeout_s."""
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:
            if (await self._fresh("the control script to start")).program_running:
                return True
            await asyncio.sleep(self.poll_s)
        return False

    async def _arm_watchdog(self) -> None:
        """setWatchdog on the script now running, once: ArmFault when the controller does not take it."""
        if self._watchdog_set:
            return
        if not await self._call("setWatchdog", "set_watchdog", self.watchdog_hz):
            reading = await self._fresh("the state after setWatchdog was refused")
            await self._raise_if_stopped(reading, "setWatchdog refused")
            raise ArmFault(f"{self.name}: the controller refused setWatchdog({self.watchdog_hz:g} Hz)")
        self._watchdog_set = True

    async def _check_tcp_offset(self) -> None:
        """Read the active TCP offset of the script now running, once (getTCPOffset): ArmFault unless it is zero
        within TCP_OFFSET_TOL_M / TCP_OFFSET_TOL_RAD, or when the controller cannot answer."""
        if self._tcp_checked:
            return
        try:
            offset = await self._call("getTCPOffset", "tcp_offset")
        except LinkLost:
            raise
        except DeviceError as exc:
            await self._no_stop_behind_refusal("cannot read the controller's TCP offset")
            raise ArmFault(f"{self.name}: cannot read the controller's active TCP offset: {exc}") from None
        self.tcp_offset = offset
        if offset is not None:
            vec = np.asarray(offset, dtype=np.float64)
            shift, turn = float(np.linalg.norm(vec[:3])), float(np.linalg.norm(vec[3:]))
            if not (math.isfinite(shift + turn) and shift <= TCP_OFFSET_TOL_M and turn <= TCP_OFFSET_TOL_RAD):
                mm = ", ".join(f"{v * 1e3:.1f}" for v in vec[:3])
                deg = ", ".join(f"{math.degrees(v):.2f}" for v in vec[3:])
                raise ArmFault(f"{self.name}: the controller's active TCP offset is [{mm}] mm, [{deg}] deg (rotation "
                               f"vector), not the bare flange that spadscan's poses and [arm] hand_eye refer to; "
                               f"select the bare-flange TCP on the teach pendant (Installation -> General -> TCP) or "
                               f"set its offset to zero, then start (or resume) again")
        self._tcp_checked = True

    async def _kick_watchdog(self) -> None:
        """Kick three times per watchdog period while the link lives (replies are not awaited: a kick queued behind
        a slow call still goes)."""
        period = 1.0 / (3.0 * self.watchdog_hz)
        while True:
            await asyncio.sleep(period)
            link = self._link
            if link is not None and link.alive:
                link.post("kickWatchdog", self.timeout_s, "kick")

    async def check_poses(self, tcp_poses: np.ndarray, first_index: int = 0) -> None:
        """Ask the controller about every TCP pose (P, 4, 4) before the first move: ArmFault naming the first one
        outside its safety limits (isPoseWithinSafetyLimits: safety planes, tool orientation limits, reach) or
        without an inverse kinematics solution (getInverseKinematicsHasSolution, where the controller answers it).
        Poses are numbered from first_index."""
        self._require_open()
        poses = np.asarray(tcp_poses, dtype=np.float64)
        if len(poses) == 0:
            return
        vecs = [[float(x) for x in pose_to_vector(p)] for p in poses]
        n = first_index + len(vecs)
        # A controller stopped for safety, or without its script, cannot answer: say which (as a move would).
        await self._raise_if_stopped(await self._fresh("the safety state before the pose checks"),
                               "the controller cannot check the planned poses")
        await self._check_tcp_offset()  # the controller checks TCP poses: they must be the flange's
        try:
            result = await self._call(f"the controller's checks of {len(vecs)} poses", "check_poses", vecs,
                                      timeout_s=self.timeout_s + 0.25 * len(vecs))
        except LinkLost:
            raise
        except DeviceError as exc:
            await self._no_stop_behind_refusal("the controller cannot check the planned poses")
            raise ArmFault(f"{self.name}: cannot ask the controller about the planned poses: {exc}") from None
        i = result["index"]
        if i >= 0:
            await self._no_stop_behind_refusal("the controller cannot check the planned poses")
            p = ", ".join(f"{v:.3f}" for v in vecs[i][:3])
            why = ("is outside the controller's safety limits (isPoseWithinSafetyLimits: its safety planes, tool "
                   "orientation limits or reach)" if result["check"] == "safety" else
                   "has no inverse kinematics solution on the controller (getInverseKinematicsHasSolution)")
            raise ArmFault(f"{self.name}: pose {first_index + i} of {n}: TCP at [{p}] m {why}")

    async def release(self) -> None:
        """Stop any motion (stopL). Nothing to do when not connected; LinkLost without trying when the link is
        known dead (ur_rtde would block for seconds on it)."""
        if self._open:
            await self._check_link(await self._read("the arm state"))
            await self.stop()

    async def close(self) -> None:
        """Stop the control script (`_stop_script`), disconnect both interfaces and end the ur_rtde process.
        Idempotent; never waits long on a dead link (the process was ended when the link was found lost, and one
        that does not exit within timeout_s is killed)."""
        await self._close_link()

    # -- acting ----------------------------------------------------------------------------------------------------
    async def move_to(self, tcp_pose: np.ndarray, speed: float | None = None, accel: float | None = None) -> None:
        """moveL to a TCP pose (4x4, base frame, metres) and wait until the arm is there (see the module docstring).

        speed / accel default to the constructor's. Raises ArmFault (safety stop, refused move, target not
        reached, bad arguments) or LinkLost (stale or closed link).
        """
        speed = self.speed if speed is None else float(speed)
        accel = self.accel if accel is None else float(accel)
        if not (0 < speed <= MAX_TOOL_SPEED and 0 < accel <= MAX_TOOL_ACCEL):
            raise ArmFault(f"{self.name}: speed {speed} m/s and acceleration {accel} m/s^2 must be in "
                           f"(0, {MAX_TOOL_SPEED:g}] and (0, {MAX_TOOL_ACCEL:g}]")
        try:
            target = pose_to_vector(tcp_pose)
        except DeviceError as exc:
            raise ArmFault(f"{self.name}: bad target: {exc}") from None
        self._require_open()
        start = await self._fresh("live data before moveL")
        await self._raise_if_stopped(start, "moveL refused")
        await self._check_tcp_offset()
        await self._arm_watchdog()
        what = f"moveL to [{target[0]:.4f}, {target[1]:.4f}, {target[2]:.4f}] m"
        vec = [float(x) for x in target]
        budget = 2.0 * _move_time(start.pose_vec, target, speed, accel) + self.timeout_s
        op_before = (await self._read(what, progress=True)).op_id
        try:
            if not await self._call(what, "moveL", vec, speed, accel):
                # ur_rtde refuses from the control stream's view, which may lag the receive stream's (a stop
                # just cleared): let both catch up, then try once more unless a real reason shows.
                await self._explain_refusal(what, final=False)
                # The refusal can also be a late answer to a command the controller did take: resend only when the
                # arm is neither moving nor at the target, so that one move is never sent twice.
                if (not await self._took_it(what, target, op_before)
                        and not await self._call(what, "moveL", vec, speed, accel)):
                    await self._explain_refusal(what, final=True)
            await self._wait_motion(what, budget, target)
            await self._wait_arrival(what, target)
        except asyncio.CancelledError:
            # Runs in the ur_rtde process as soon as it is free.
            if self._link is not None:
                self._link.post("stopL after a cancelled move", self.timeout_s, "stopL", STOP_DECEL)
            raise

    async def state(self) -> ArmState:
        """Actual TCP pose (4x4), joints (6,), controller timestamp, and which safety stop holds the arm, if one does
        (emergency, protective or safeguard stop). Raises LinkLost when the link is closed or the data stopped
        advancing."""
        self._require_open()
        reading = await self._read("the arm state")
        await self._check_link(reading)
        return ArmState(tcp_pose=vector_to_pose(reading.pose_vec), joints=reading.joints.copy(),
                         timestamp_s=reading.timestamp, safety_stop=reading.stop)

    async def read_speed_slider(self) -> None:
        """One read of the receive interface (getTargetSpeedFraction among the rest), for the slider alone: no
        check of the link (a stale link's reading does not renew `speed_slider_at`), so that asking for it (`ctl
        status` while paused) never ends the link. LinkLost when it is known down."""
        self._require_open()
        await self._read("the speed slider")

    async def stop(self) -> None:
        """stopL now (decelerating at STOP_DECEL). LinkLost without trying when the link is dead: stopL would block
        the ur_rtde process for good."""
        self._require_open()
        await self._check_link(await self._read("the arm state before stopL"))
        await self._call("stopL", "stopL", STOP_DECEL)

    # -- waiting ---------------------------------------------------------------------------------------------------
    async def _wait_motion(self, what: str, budget_s: float, target: np.ndarray) -> None:
        """Poll until the move ends. Its budget counts motion time: wall time at the controller's speed scaling
        (the pendant's slider at 0.25 makes a move take four times as long).

        The control script answers an asynchronous moveL at once and reports the move running only when its move
        thread first runs, a controller cycle later (ur_rtde's examples wait for that start): "not running" ends the
        wait only once the move was seen running, or the arm is at the target, or START_GRACE_S has passed."""
        spent, last, slowest = 0.0, time.monotonic(), 1.0
        started, start_by = False, time.monotonic() + START_GRACE_S
        while True:
            reading = await self._read(what, progress=True)
            await self._check_link(reading)
            await self._raise_if_stopped(reading, f"{what} aborted")
            started = started or reading.moving
            if not reading.moving and (started or time.monotonic() > start_by or self._at(reading, target)):
                return
            now = time.monotonic()
            scaling = min(1.0, max(MIN_SPEED_SCALING, reading.speed_scaling))
            spent, last, slowest = spent + (now - last) * scaling, now, min(slowest, scaling)
            if spent > budget_s:
                await self.stop()
                slowed = f" (speed scaling down to {slowest:.2f})" if slowest < 1.0 else ""
                raise ArmFault(f"{self.name}: {what} did not finish within {budget_s:.1f} s of motion time"
                               f"{slowed}; stopped")
            await asyncio.sleep(self.poll_s)

    async def _wait_arrival(self, what: str, target: np.ndarray) -> None:
        """Wait for a reading at the target and at rest: the receive stream may lag the control stream's 'done'."""
        deadline = time.monotonic() + self.timeout_s
        first_ts = None
        while True:
            reading = await self._read(what)
            await self._check_link(reading)
            await self._raise_if_stopped(reading, f"{what} aborted")
            first_ts = reading.timestamp if first_ts is None else first_ts
            dist, angle = _pose_distance(reading.pose_vec, target)
            speed, spin = (float(np.linalg.norm(reading.tcp_speed[i:i + 3])) for i in (0, 3))
            if (dist <= self.position_tol_m and angle <= self.rotation_tol_rad and speed <= self.rest_speed
                    and spin <= self.rest_angular_speed):
                return
            if time.monotonic() > deadline and reading.timestamp != first_ts:
                raise ArmFault(f"{self.name}: {what} ended {dist * 1e3:.2f} mm / {math.degrees(angle):.3f} deg "
                               f"from the target, moving at {speed * 1e3:.1f} mm/s / {math.degrees(spin):.2f} deg/s "
                               f"(tolerance {self.position_tol_m * 1e3:g} mm / "
                               f"{math.degrees(self.rotation_tol_rad):g} deg, at rest below "
                               f"{self.rest_speed * 1e3:g} mm/s / {math.degrees(self.rest_angular_speed):g} deg/s)")
            await asyncio.sleep(self.poll_s)

    async def _took_it(self, what: str, target: np.ndarray, op_before: int) -> bool:
        """Whether fresh readings show the arm at the target or a move started since `op_before` (the operation id
        before the refused moveL). A running bit under the same id is a move a safety stop halted (its thread lives
        on, so the bit stays set): a new move would show a new id within START_GRACE_S, else it was not taken."""
        deadline = time.monotonic() + START_GRACE_S
        while True:
            await self._fresh(f"the motion state after {what} was refused")
            reading = await self._read(what, progress=True)
            if self._at(reading, target) or (reading.moving and reading.op_id != op_before):
                return True
            if not reading.moving or time.monotonic() > deadline:
                return False
            await asyncio.sleep(self.poll_s)

    def _at(self, reading: _Reading, target: np.ndarray) -> bool:
        """Whether `reading`'s TCP pose is within the tolerances of `target`."""
        dist, angle = _pose_distance(reading.pose_vec, target)
        return dist <= self.position_tol_m and angle <= self.rotation_tol_rad

    async def _fresh(self, what: str) -> _Reading:
        """A reading whose controller timestamp is newer than any seen so far; LinkLost after stale_after_s."""
        self._require_open()
        start, before = time.monotonic(), self._last_ts
        while True:
            reading = await self._read(what)
            if not reading.connected:
                raise await self._lost(f"link closed while waiting for {what}")
            if reading.timestamp != before:
                self._seen(reading.timestamp)
                return reading
            waited = time.monotonic() - start
            if waited > self.stale_after_s:
                raise await self._lost(f"receive data stale: controller timestamp stuck at {reading.timestamp:.3f} s "
                                       f"for {waited:.2f} s (limit {self.stale_after_s:g} s) while waiting for {what}")
            await asyncio.sleep(self.poll_s)

    def _seen(self, ts: float) -> None:
        if ts != self._last_ts:
            self._last_ts, self._last_change = ts, time.monotonic()

    async def _check_link(self, reading: _Reading) -> None:
        """LinkLost when the link is closed or the timestamp has not moved for stale_after_s."""
        if not reading.connected:
            raise await self._lost("link closed (ur_rtde reports disconnected)")
        if reading.timestamp != self._last_ts:
            self._seen(reading.timestamp)
            return
        age = time.monotonic() - self._last_change
        if age > self.stale_after_s:
            raise await self._lost(f"receive data stale: controller timestamp stuck at {reading.timestamp:.3f} s for "
                                   f"{age:.2f} s (limit {self.stale_after_s:g} s)")

    async def _raise_if_stopped(self, reading: _Reading, doing: str) -> None:
        """ArmFault for a safety stop (emergency, protective, safeguard) or a control script that is not running.

        Whether the script runs comes from the control interface's stream, the safety flags from the receive
        interface's: a controller that stops the script on a safety stop can show the first before the second. A
        script seen stopped with no safety flag is therefore read again for up to SAFETY_CATCH_UP_S, so that the
        fault is named by its cause."""
        deadline = time.monotonic() + SAFETY_CATCH_UP_S
        while not reading.program_running and reading.stop is None and time.monotonic() < deadline:
            reading = await self._fresh(f"the safety state after {doing}")
        stop = reading.stop
        if stop is not None:
            raise ArmFault(f"{stop} on {self.name}: {doing} ({_mode_text(reading.safety_mode)}; "
                           f"{clear_advice(stop)})")
        if not reading.program_running:
            self._watchdog_set = self._tcp_checked = False  # the program uploaded next is asked afresh
            unpowered = not_ready(reading.robot_mode)
            if unpowered is not None:
                raise ArmFault(f"{self.name}: {doing}: {unpowered}")
            raise ArmFault(f"{self.name}: {doing}: the RTDE control script is not running on the controller "
                           f"({_mode_text(reading.safety_mode)}; the watchdog stops it when the daemon falls silent "
                           f"for {1 / self.watchdog_hz:g} s, a safety stop or the pendant can stop it too); resuming "
                           f"the scan uploads it again")

    async def _no_stop_behind_refusal(self, doing: str) -> _Reading:
        """ArmFault naming a safety stop that shows within SAFETY_CATCH_UP_S of a query refused or failed: a
        controller that has just stopped for safety refuses every query, and the receive stream, which carries the
        safety flags, can show the stop only after the refusal came. Read until then before blaming the query (it
        is about to fail anyway: the wait costs nothing that counts). Returns the last reading."""
        deadline = time.monotonic() + SAFETY_CATCH_UP_S
        while True:
            reading = await self._fresh(f"the safety state after {doing}")
            await self._raise_if_stopped(reading, doing)
            if time.monotonic() >= deadline:
                return reading

    async def _explain_refusal(self, what: str, final: bool) -> None:
        """The controller answered False: raise for a safety stop or a dead link; otherwise, when `final`, raise a
        plain refusal once no stop has shown for SAFETY_CATCH_UP_S (`_no_stop_behind_refusal`), else return after two
        fresh readings (time for the control stream to catch up before the one retry)."""
        if not final:
            for _ in range(2):
                await self._raise_if_stopped(await self._fresh(f"the safety state after {what} was refused"),
                                             f"{what} refused")
            return
        reading = await self._no_stop_behind_refusal(f"{what} refused")
        running = await self._call("the program state", "program_running")
        raise ArmFault(f"{self.name}: controller refused {what} ({_mode_text(reading.safety_mode)}, control "
                       f"script {'running' if running else 'not running'})")

    # -- the ur_rtde process --------------------------------------------------------------------------------------
    async def _call(self, what: str, op: str, *args, timeout_s: float | None = None):
        """Run a `rtde_child` operation; LinkLost when not connected, the link has ended or no answer comes in time."""
        if self._link is None:
            raise LinkLost(f"{self.name}: not connected; {what} not sent")
        return await self._link.call(what, self.timeout_s if timeout_s is None else timeout_s, op, *args)

    async def _read(self, what: str, progress: bool = False) -> _Reading:
        d = await self._call(what, "read_progress" if progress else "read")
        self._note_slider(d.get("speed_slider"), float(d["timestamp"]))
        return _Reading(np.array(d["pose"], dtype=np.float64), np.array(d["joints"], dtype=np.float64),
                        float(d["timestamp"]), d["protective"], d["emergency"], d["safety_mode"], d["connected"],
                        np.array(d["tcp_speed"], dtype=np.float64), bool(d.get("moving", False)),
                        int(d["safety_bits"]), bool(d["program_running"]), float(d["speed_scaling"]),
                        int(d.get("op_id", -1)), bool(d.get("paused", False)),
                        int(d.get("robot_mode", ROBOT_MODE_RUNNING)))

    def _note_slider(self, slider: float | None, timestamp: float) -> None:
        """Keep the speed slider's reading, and when it came (`speed_slider_at`: only a reading the controller sent
        since the last one, at controller time `timestamp`); the log says once when it drops below 100 % and when it
        is back."""
        if slider is None:
            return
        if timestamp != self._slider_ts:
            self._slider_ts, self.speed_slider_at = timestamp, time.monotonic()
        was, self.speed_slider = self.speed_slider, float(slider)
        slowed, was_slowed = self.speed_slider < SLIDER_FULL, was is not None and was < SLIDER_FULL
        if slowed and not was_slowed:
            log.warning("%s: %s", self.name, slider_note(self.speed_slider))
        elif was_slowed and not slowed:
            log.info("%s: the controller runs moves at full speed again (the pendant's speed slider at 100 %%)",
                     self.name)

    async def _lost(self, reason: str) -> LinkLost:
        """Send a last stopL (it may still get through: a link found stale can carry commands), end the ur_rtde
        process (its interfaces are of no more use and would go on reconnecting by themselves) and return the
        LinkLost to raise; later calls fail with the same reason until a reconnect."""
        if self._link is not None:
            await self._link.last_call(reason, STOP_ON_LOSS_S, "stopL before dropping the link", "stopL", STOP_DECEL)
        return LinkLost(f"{self.name}: {reason}")

    def _require_open(self) -> None:
        if not self._open:
            raise LinkLost(f"{self.name}: not connected")

    async def _close_link(self) -> None:
        """Stop the kicks and the control script of an open link, then end the ur_rtde process."""
        kicker, self._kicker = self._kicker, None
        if kicker is not None:
            kicker.cancel()
            await asyncio.gather(kicker, return_exceptions=True)
        link = self._link
        try:
            if self._open and link is not None and link.alive:
                await self._stop_script()
        finally:  # also when cancelled: the process is ended all the same
            self._open, self._link = False, None
            if link is not None:
                await link.stop(grace_s=self.timeout_s)

    async def _stop_script(self) -> None:
        """End the control script before disconnecting (stopScript; ur_rtde's disconnect() leaves it running). Not
        over a link whose data is stale (it is ended instead), nor while a safety stop holds the script (it takes no
        command then: ur_rtde gives up at once under a protective or emergency stop, and under a safeguard stop waits
        up to 300 s for an answer that does not come): the watchdog stops it there, armed unless that stop held the
        script since connect (the warning then says to stop it on the pendant). Never raises LinkLost or
        DeviceError: a close goes on."""
        watchdog = (f"the controller's watchdog stops it within {1 / self.watchdog_hz:g} s" if self._watchdog_set
                    else "no watchdog was armed on it: stop it on the teach pendant")
        try:
            reading = await self._fresh("the control script's state before stopScript")
            if reading.paused:
                await self._stop_paused_program()
                return
            if not reading.program_running:
                return
            if reading.stop is not None:
                log.warning("%s: the control script was left running (%s holds it); %s", self.name, reading.stop,
                            watchdog)
                return
            result = await self._call("stopScript", "stop_script")
        except DeviceError as exc:  # LinkLost too
            log.warning("%s: could not stop the control script (%s); %s", self.name, self._unnamed(exc), watchdog)
            return
        if not result["stopped"]:
            log.warning("%s: the control script was left running (%s); %s", self.name, result["why"], watchdog)

    async def _stop_paused_program(self) -> None:
        """A protective or emergency stop paused the program (UR: it only pauses it) and no script command reaches a
        paused program, so stopScript cannot end it: the dashboard's `stop` does. Left paused, the program would
        finish its halted move when someone presses Play on the pendant, long after this daemon let go of the arm.
        Raises DeviceError (LinkLost too) as `_call` does; the caller says what is left."""
        result = await self._call("the dashboard's stop for the paused program", "stop_script")
        if result["stopped"]:
            log.info("%s: the paused control script was stopped (the dashboard's stop)", self.name)
        else:
            log.warning("%s: the paused control script was left on the controller (%s): stop it on the teach pendant "
                        "(Play would finish its halted move)", self.name, result["why"])

    def _unnamed(self, exc: Exception) -> str:
        """The message of an error this arm raised, without its leading "<arm name>: " (for a line that names the arm
        already)."""
        text, prefix = str(exc), f"{self.name}: "
        return text[len(prefix):] if text.startswith(prefix) else text


def _mode_text(mode: int) -> str:
    """A safety mode by number and by name (RTDE guide), for messages."""
    return f"safety mode {mode} ({SAFETY_MODES.get(mode, 'unknown')})"


def _pose_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(translation metres, rotation radians) between two pose vectors (6,): position and rotation vector."""
    return (float(np.linalg.norm(a[:3] - b[:3])),
            rotation_angle(rotvec_to_matrix(a[3:]), rotvec_to_matrix(b[3:])))


def _move_time(start: np.ndarray, goal: np.ndarray, speed: float, accel: float) -> float:
    """Rough duration (s) of a linear move between pose vectors (6,): trapezoid on max(translation, 0.1 m x angle)."""
    dist, angle = _pose_distance(start, goal)
    d = max(dist, 0.1 * angle)
    return d / speed + speed / accel if d > speed * speed / accel else 2.0 * math.sqrt(d / accel)
