"""State of the simulated UR controller: robot and safety modes, RTDE registers, the control script, motion.

The model is driven by three things: RTDE input packages (`write_inputs`), the script port (`start_script`) and
the fault API (`set_protective_stop`, ...). It is thread-safe (one lock) so that tests may inject faults from their
own thread while the server's event loop streams. Time is controller seconds since the model was created; motion
durations are multiplied by `time_scale` so that tests run fast.

The control script uploaded by ur_rtde is not interpreted; its register protocol is emulated instead (ur_rtde
1.6.5's script, `rtde_control.script`):
`input_int_register_0` carries a command, `output_int_register_0` is 1 (ready) while the command register is 0, a
command is taken once, and `output_int_register_0` becomes 2 when it is done; `input_int_register_1` = 1 makes a move
asynchronous (done at once; `output_int_register_2` reports the move running, bit 15, once its thread has started,
THREAD_START_S later, and then finished). As in ur_rtde's script, only two things write "finished": the move
thread when its move ends, and a command that kills the thread (stopL/stopJ, the next move) or a new program. A
safety stop halts the arm and leaves the thread, and so the running bit, as they were; a program stopped (the
watchdog, a script error) writes nothing either: no script code runs then (`_halt`).
Queries answer in `output_int_register_1` (1 = yes): 36 is_within_safety_limits(pose), 60/61
get_inverse_kin_has_solution(pose[, qnear, errors]), from the model's reach (`kinematics.reachable`) and its safety
planes. 40 get_tcp_offset: the script writes the URScript get_tcp_offset() (the active TCP offset, a pose vector
[m, rad] in the flange frame: `tcp_offset`, zero - the bare flange - by default) to `output_double_register_0..5`
and signals done, and ur_rtde's getTCPOffset reads those six registers (the script has those lines from controller
3.6 on). The reported TCP poses stay the model's own: it has no flange that an offset would move.
35 set_watchdog: `rtde_set_watchdog("input_int_register_0", f, "stop")`, so an input package that writes the
command register must arrive at least every 1/f s (ur_rtde's kickWatchdog writes 0 there), or the program stops
(runtime STOPPED) and the arm halts where it is. Until a program sets it there is no watchdog: a program whose client
went away without setting one runs on. A program's watchdog ends with it (a new program sets its own).
255 stop script (ur_rtde's stopScript): taken like any command (only while no safety stop holds the script), it
signals nothing (no "done": ur_rtde waits for the program to stop instead), ends the script's main loop and with it
the program (runtime STOPPED), and the program's watchdog with it; an asynchronous move's thread ends with the program
and writes nothing (`_halt`). ur_rtde's disconnect() sends no such command: a client that only disconnects leaves
the program running.

Safety stops follow the RTDE guide: safety_mode 3 protective (status bit 2), 5 safeguard (bit 4), 7 robot
emergency (bits 6, 7), each with bit 10 "stopped due to safety" (`safety_mode()`, which the dashboard's safetymode
and safetystatus name too). The script takes no command while one is active. A protective or emergency stop also
pauses the program (UR's ROS 2 driver documentation: such a stop "is only pausing the running program"; runtime_state
4, PAUSED, UR's client library's RUNTIME_STATE): the move thread is held where the arm stopped, and the program stays
paused when the stop is cleared. A paused program is not running to ur_rtde (its isProgramRunning is runtime_state ==
PLAYING), takes no command, and is replaced by the next upload (ur_rtde's reuploadScript sends the script without
stopping a program that is not playing). Resuming it in place (the pendant's or the dashboard's play) is not modelled.
A safeguard stop holds the program without pausing it: it takes commands again once the stop is cleared.
A safety violation (safety_mode 8, status bit 8) or fault (9, bit 9) is the safety system itself stopping the arm
(UR's manuals: a category 0 stop, power removed): the arm halts where it is, the program always stops, and no
program starts (a script that arrives is recorded, not run) until `restart_safety` - what restarting the arm from
the pendant, or the dashboard's `restart safety`, does; unlocking a protective stop does not clear it. The arm comes
back from that restart powered off (robot_mode 3, POWER_OFF), and runs no program (a script that arrives is recorded,
not run) until it is powered on (the dashboard's `power on`: 5, IDLE, its brakes on) and its brakes are released
(`brake release`: 7, RUNNING; UR's robot modes, as ur_rtde's getRobotMode lists them); `power off` takes it back to 3
and ends the program. The program stays stopped until the script is uploaded again.

What a real arm adds to the ideal: `pose_noise_m` (the reported actual TCP position scatters by that standard
deviation, per axis, per package) and `speed_slider` (the pendant's speed slider, target_speed_fraction: motion runs at
that fraction of its programmed speed, so moves take 1/slider as long).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from spadscan.daemon.arm.pose_convert import matrix_to_rotvec, rotvec_to_matrix
from spadscan.daemon.ursim.kinematics import Motion, forward_kinematics, inverse_kinematics, reachable
from spadscan.daemon.ursim.variables import OUTPUT_TYPES, ZERO

MOVE_COMMANDS = {1: "moveJ", 2: "moveJ_IK", 3: "moveL", 4: "moveL_FK"}
STOP_COMMANDS = {33: "stopL", 34: "stopJ"}
SET_WATCHDOG, IS_POSE_WITHIN_SAFETY_LIMITS, IK_HAS_SOLUTION, IK_HAS_SOLUTION_ARGS = 35, 36, 60, 61
GET_TCP_OFFSET = 40
STOP_SCRIPT = 255
THREAD_START_S = 0.008
"""Controller seconds from an asynchronous move's "done" to its thread's "started" in the progress register: one
cycle of a CB-series controller (125 Hz; ur_rtde's examples wait for the start before they wait for the end)."""

RUNTIME_STOPPED, RUNTIME_PLAYING, RUNTIME_PAUSED = 1, 2, 4
ROBOT_MODE_POWER_OFF, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 5, 7
ROBOT_MODE_NAMES = {ROBOT_MODE_POWER_OFF: "POWER_OFF", ROBOT_MODE_IDLE: "IDLE", ROBOT_MODE_RUNNING: "RUNNING"}
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP, SAFETY_SAFEGUARD_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 1, 3, 5, 7
SAFETY_VIOLATION, SAFETY_FAULT = 8, 9
SAFETY_MODE_NAMES = {SAFETY_NORMAL: "NORMAL", SAFETY_PROTECTIVE_STOP: "PROTECTIVE_STOP",
                     SAFETY_SAFEGUARD_STOP: "SAFEGUARD_STOP", SAFETY_ROBOT_EMERGENCY_STOP: "ROBOT_EMERGENCY_STOP",
                     SAFETY_VIOLATION: "VIOLATION", SAFETY_FAULT: "FAULT"}
"""The safety modes the model takes, by the names the dashboard gives them (the RTDE guide's SafetyMode names)."""
BIT_NORMAL, BIT_PROTECTIVE_STOPPED, BIT_SAFEGUARD_STOPPED = 1 << 0, 1 << 2, 1 << 4
BIT_ROBOT_ESTOP, BIT_EMERGENCY_STOPPED, BIT_STOPPED_DUE_TO_SAFETY = 1 << 6, 1 << 7, 1 << 10
BIT_VIOLATION, BIT_FAULT = 1 << 8, 1 << 9
STATUS_POWER_ON, STATUS_PROGRAM_RUNNING = 1 << 0, 1 << 1
JOINT_RUNNING_MODE = 253


@dataclass(frozen=True)
class MoveRecord:
    """A command the controller took: name (moveL, stopL, ...), its number, the six values of
    input_double_register_0..5 (pose vector or joint angles), speed and acceleration (registers 6, 7), async flag,
    and the controller time it was taken."""

    name: str
    command: int
    target: tuple[float, ...]
    speed: float
    accel: float
    asynchronous: bool
    t: float


class URControllerModel:
    """What a UR controller running ur_rtde's control script would report; see the module docstring."""

    def __init__(self, *, time_scale: float = 1.0, initial_pose=(0.3, 0.0, 0.3, 0.0, math.pi, 0.0), seed: int = 0):
        self.time_scale = float(time_scale)
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self._pose = np.asarray(initial_pose, dtype=np.float64)
        self._rng = np.random.default_rng(seed)
        # Motion time runs at the speed slider's rate: tau(t) = tau_ref + (t - t_ref) * speed_slider.
        self.speed_slider = 1.0
        self._t_ref = self._tau_ref = 0.0
        self.pose_noise_m = 0.0
        self.safety_floor_z: float | None = None
        """A safety plane: TCP positions below this height (m) are outside the safety limits."""
        self.reach_m = 0.85
        self.tcp_offset: tuple[float, ...] = (0.0,) * 6
        """The active TCP offset the pendant sets (pose vector [m, rad], flange frame), as get_tcp_offset answers it."""
        self.tcp_offset_reads = 0
        """Times the script answered get_tcp_offset (command 40)."""
        self.watchdog_period_s: float | None = None  # set by set_watchdog (cmd 35) until the program stops
        self._last_kick = 0.0
        self.watchdog_stops = 0
        """Times the RTDE watchdog stopped the program."""
        self.script_stops = 0
        """Times the control script ended on its stop command (255, ur_rtde's stopScript)."""
        self.dashboard_stops = 0
        """Times the dashboard's `stop` ended a playing or paused program."""
        self.queries: list[tuple[str, tuple[float, ...], bool]] = []
        """(query, pose, answer) of every safety-limit and inverse-kinematics question answered."""
        self._motion: Motion | None = None
        self._motion_async = False
        self._move_thread = False
        """An asynchronous move's thread is alive: its "finished" is not written yet (it may be halted by a safety
        stop, the arm at rest, and still be alive)."""
        self.move_thread_start_s = THREAD_START_S
        """Controller seconds from an asynchronous move's "done" to its "running" (THREAD_START_S)."""
        self._async_start_at: float | None = None
        """Controller time at which a move thread just started reports itself running (see THREAD_START_S)."""
        self._inputs: dict[str, object] = {}
        self._out_int = [0] * 48
        self._out_double = [0.0] * 48
        self.runtime_state = RUNTIME_STOPPED
        self.protective_stop = False
        self.safeguard_stop = False
        self.emergency_stop = False
        self.safety_fault: int | None = None
        self.robot_mode = ROBOT_MODE_RUNNING
        """SAFETY_VIOLATION or SAFETY_FAULT while the safety system holds the arm (until `restart_safety`)."""
        self._busy = False  # a synchronous command is executing (the script is blocked in it)
        self._executing = False  # the script took the current command and waits for the register to clear
        self._async_writes = 0
        self._async_op = 0
        self.moves: list[MoveRecord] = []
        self.errors: list[str] = []
        """Script errors (a command the script could not carry out; the script stopped)."""
        self.scripts: list[str] = []

    # -- time and motion -------------------------------------------------------------------------------------
    def now(self) -> float:
        """Controller time (s) since start."""
        return time.monotonic() - self._t0

    def _tau(self, t: float) -> float:
        """Motion time at controller time t: it runs at the speed slider's rate."""
        return self._tau_ref + (t - self._t_ref) * self.speed_slider

    def set_speed_slider(self, fraction: float) -> None:
        """The pendant's speed slider, 0 < fraction <= 1: motion continues at that fraction of its speed."""
        if not (math.isfinite(fraction) and 0.0 < fraction <= 1.0):
            raise ValueError(f"speed slider must be in (0, 1], got {fraction}")
        with self._lock:
            t = self.now()
            self._tau_ref, self._t_ref = self._tau(t), t
            self.speed_slider = float(fraction)

    def _advance(self, t: float) -> None:
        """Bring the motion to time t; finish it (and signal the script) when it has arrived."""
        if self._async_start_at is not None and t >= self._async_start_at:
            self._async_start_at = None
            self._write_async(0)  # the move thread runs: "started"
        m = self._motion
        if m is None:
            return
        tau = self._tau(t)
        if tau < m.end_time():
            self._pose = m.pose_at(tau)
            return
        goal = m.goal if m.linear else forward_kinematics(m.goal)
        self._pose = np.concatenate([goal[:3], matrix_to_rotvec(rotvec_to_matrix(goal[3:]))])
        self._motion = None
        if self._motion_async:
            if self._async_start_at is not None:  # a move shorter than the thread's start: it started, then ended
                self._async_start_at = None
                self._write_async(0)
            self._move_thread = False
            self._write_async(-1)
        elif self._busy:
            self._busy = False
            self._out_int[0] = 2

    def _halt(self, t: float, thread: str = "killed") -> None:
        """Stop where the arm is now. What becomes of an asynchronous move's thread: "killed" by a command
        (stopL/stopJ, the next move, a new program), and "finished" is written for it, as ur_rtde's script does where
        it kills the thread; "ended" with the program (the watchdog, a script error, stopScript): no script code runs
        any more, and the register keeps what it said; "held" by a safety stop: the thread lives on, halted, and
        nothing is written. Only "killed" clears the running bit."""
        if self._motion is not None:
            self._pose = self._motion.pose_at(self._tau(t))
            self._motion = None
        if thread == "held" or not self._move_thread:
            return
        self._move_thread = False
        self._async_start_at = None  # a thread that dies before it ran never says it started
        if thread == "killed":
            self._write_async(-1)

    def _write_async(self, value: int) -> None:
        """ur_rtde's async progress register: change count in bits 16-23, operation id 24-30, running bit 15."""
        self._async_writes = (self._async_writes + 1) % 128
        if value == 0:
            self._async_op = (self._async_op + 1) % 128
        reg = self._async_writes * 65536 + self._async_op * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self._out_int[2] = reg

    # -- the control script ------------------------------------------------------------------------------------
    def start_script(self, text: str) -> None:
        """A complete program arrived on the script port: (re)start it; it reports ready."""
        with self._lock:
            t = self.now()
            self._halt(t)
            self.scripts.append(text)
            if self.safety_fault is not None or self.robot_mode != ROBOT_MODE_RUNNING:
                return  # no program starts until the arm is restarted, powered on and its brakes released
            self.runtime_state = RUNTIME_PLAYING
            self.watchdog_period_s = None  # a new program has set no watchdog yet
            self._busy = self._executing = False
            self._write_async(-1)
            self._out_int[0] = 1
            self._step(t)

    def write_inputs(self, values: dict[str, object]) -> None:
        """Values of one RTDE input package (name -> value); the script reacts at once."""
        with self._lock:
            t = self.now()
            self._advance(t)
            if "input_int_register_0" in values:  # what the watchdog watches
                self._last_kick = t
            self._inputs.update(values)
            self._step(t)

    def _safety_stopped(self) -> bool:
        return self.protective_stop or self.safeguard_stop or self.emergency_stop or self.safety_fault is not None

    def _step(self, t: float) -> None:
        """One pass of the script's main loop (it is paused while the robot is stopped for safety)."""
        if self.runtime_state != RUNTIME_PLAYING or self._busy or self._safety_stopped():
            return
        cmd = int(self._inputs.get("input_int_register_0", 0))
        if cmd == 0:
            self._executing = False
            self._out_int[0] = 1
        elif not self._executing:
            self._executing = True
            self._process(cmd, t)

    def _process(self, cmd: int, t: float) -> None:
        regs = [float(self._inputs.get(f"input_double_register_{i}", 0.0)) for i in range(8)]
        asynchronous = int(self._inputs.get("input_int_register_1", 0)) == 1
        if cmd == STOP_SCRIPT:  # the main loop ends without signalling done; the program ends with it
            self._end_program(t)
            self.script_stops += 1
            return
        if cmd == SET_WATCHDOG:
            self.watchdog_period_s = 1.0 / regs[0] if math.isfinite(regs[0]) and regs[0] > 0 else None
            self._last_kick = t
            self._out_int[0] = 2
            return
        if cmd == GET_TCP_OFFSET:
            self._out_double[0:6] = [float(x) for x in self.tcp_offset]
            self.tcp_offset_reads += 1
            self._out_int[0] = 2
            return
        if cmd in (IS_POSE_WITHIN_SAFETY_LIMITS, IK_HAS_SOLUTION, IK_HAS_SOLUTION_ARGS):
            self._answer(cmd, np.asarray(regs[:6]))
            self._out_int[0] = 2
            return
        name = MOVE_COMMANDS.get(cmd) or STOP_COMMANDS.get(cmd) or f"command {cmd}"
        if cmd in MOVE_COMMANDS and not (all(map(math.isfinite, regs)) and regs[6] > 0 and regs[7] > 0):
            # A real controller raises a script error here and the program halts.
            self.errors.append(f"{name}: target {regs[:6]} speed {regs[6]} acceleration {regs[7]} rejected")
            self._end_program(t)
            return
        self.moves.append(MoveRecord(name, cmd, tuple(regs[:6]), regs[6], regs[7], asynchronous, t))
        if cmd in MOVE_COMMANDS:
            goal = np.asarray(regs[:6])
            linear = cmd in (3, 4)
            if cmd == 2:
                goal = inverse_kinematics(goal)
            elif cmd == 4:
                goal = forward_kinematics(goal)
            self._halt(t)
            self._motion = Motion.plan(linear, self._pose, goal, regs[6], regs[7], self._tau(t), self.time_scale)
            self._motion_async = self._move_thread = asynchronous
            if asynchronous:
                # The script answers "done" at once and starts a move thread, which reports itself running when it
                # first runs, on a later cycle: a caller that reads the register at once may still see no move.
                self._async_start_at = t + self.move_thread_start_s
            else:
                self._busy = True
                self._advance(t)
                return
        elif cmd in STOP_COMMANDS:
            self._halt(t)
        self._out_int[0] = 2

    def _answer(self, cmd: int, pose: np.ndarray) -> None:
        """A query's answer in output_int_register_1: 1 yes, 0 no."""
        ok = bool(np.all(np.isfinite(pose))) and reachable(pose, self.reach_m)
        name = "has_ik_solution"
        if cmd == IS_POSE_WITHIN_SAFETY_LIMITS:
            name = "within_safety_limits"
            ok = ok and (self.safety_floor_z is None or bool(pose[2] >= self.safety_floor_z))
        self.queries.append((name, tuple(float(x) for x in pose), ok))
        self._out_int[1] = int(ok)

    def stop_program(self) -> None:
        """The dashboard's `stop` (as the pendant's Stop button): a playing or paused program ends, the move thread
        with it; a paused one is the case that matters, since no script command reaches it (UR's ROS 2 driver's
        robot state helper stops a paused program so before playing it again). Nothing when no program runs."""
        with self._lock:
            t = self.now()
            self._advance(t)
            if self.runtime_state not in (RUNTIME_PLAYING, RUNTIME_PAUSED):
                return
            self._end_program(t)
            self.dashboard_stops += 1

    def _end_program(self, t: float) -> None:
        """The program ends (its stop command, a script error, the watchdog, the dashboard's stop, a safety fault):
        the arm halts where it is, the move thread ends with it, and the watchdog it set goes."""
        self._halt(t, "ended")
        self._busy = self._executing = False
        self.runtime_state = RUNTIME_STOPPED
        self.watchdog_period_s = None

    def _check_watchdog(self, t: float) -> None:
        """Stop the program when the watchdog's input has not been written for longer than its period."""
        period = self.watchdog_period_s
        if period is None or self.runtime_state != RUNTIME_PLAYING or t - self._last_kick <= period:
            return
        self._end_program(t)
        self.watchdog_stops += 1
        self.errors.append(f"RTDE watchdog: input_int_register_0 not written for {t - self._last_kick:.3f} s "
                           f"(limit {period:.3f} s); program stopped")

    def watchdog_due(self) -> bool:
        """Whether the watchdog would stop the program now. The server asks, lets any input that is already waiting
        on its sockets arrive, then calls `check_watchdog`: a real controller runs in real time, a simulated one can
        be descheduled, and its own delay must not count against the client."""
        with self._lock:
            period = self.watchdog_period_s
            return (period is not None and self.runtime_state == RUNTIME_PLAYING
                    and self.now() - self._last_kick > period)

    def check_watchdog(self) -> None:
        """Stop the program if the watchdog is due (see `watchdog_due`)."""
        with self._lock:
            t = self.now()
            self._advance(t)
            self._check_watchdog(t)

    # -- faults --------------------------------------------------------------------------------------------------
    def set_protective_stop(self, on: bool) -> None:
        """Protective stop: motion halts and the program pauses (see the module docstring); clearing the stop leaves
        it paused until the script is uploaded again."""
        self._set_safety(protective=on)

    def set_safeguard_stop(self, on: bool) -> None:
        """Safeguard stop (a light curtain, a door), safety mode 5, bit 4: motion halts and the program takes no
        command until the stop is cleared; the program is not paused."""
        self._set_safety(safeguard=on)

    def set_emergency_stop(self, on: bool) -> None:
        """Robot emergency stop: like a protective stop (the program pauses), reported as safety mode 7."""
        self._set_safety(emergency=on)

    def set_safety_fault(self, mode: int) -> None:
        """The safety system stops the arm: SAFETY_VIOLATION (a safety limit was not kept) or SAFETY_FAULT (an error
        in the safety system). The arm halts, the program stops, and both stay so until `restart_safety`."""
        if mode not in (SAFETY_VIOLATION, SAFETY_FAULT):
            raise ValueError(f"a safety fault is safety mode {SAFETY_VIOLATION} or {SAFETY_FAULT}, got {mode}")
        with self._lock:
            t = self.now()
            self._advance(t)
            self.safety_fault = mode
            self._end_program(t)

    def restart_safety(self) -> None:
        """The arm restarted from the pendant (or the dashboard's `restart safety`): a violation or fault is cleared,
        the arm comes back powered off, and the program stays stopped until the script is uploaded again. Without a
        violation or fault: nothing."""
        with self._lock:
            if self.safety_fault is not None:
                self.safety_fault = None
                self.robot_mode = ROBOT_MODE_POWER_OFF

    def power_on(self) -> None:
        """The dashboard's `power on`: a powered-off arm is powered, its brakes still on (IDLE)."""
        with self._lock:
            if self.robot_mode == ROBOT_MODE_POWER_OFF:
                self.robot_mode = ROBOT_MODE_IDLE

    def release_brakes(self) -> None:
        """The dashboard's `brake release`: a powered arm with its brakes on is ready to run a program (RUNNING)."""
        with self._lock:
            if self.robot_mode == ROBOT_MODE_IDLE:
                self.robot_mode = ROBOT_MODE_RUNNING

    def power_off(self) -> None:
        """The dashboard's `power off`: the arm halts, the program ends, and the arm is powered off."""
        with self._lock:
            t = self.now()
            self._advance(t)
            if self.runtime_state in (RUNTIME_PLAYING, RUNTIME_PAUSED):
                self._end_program(t)
            self.robot_mode = ROBOT_MODE_POWER_OFF

    def _set_safety(self, protective: bool | None = None, safeguard: bool | None = None,
                    emergency: bool | None = None) -> None:
        with self._lock:
            t = self.now()
            self._advance(t)
            for name, value in (("protective_stop", protective), ("safeguard_stop", safeguard),
                                ("emergency_stop", emergency)):
                if value is not None:
                    setattr(self, name, value)
            if self._safety_stopped():
                self._halt(t, "held")
                self._busy = False
                if (self.protective_stop or self.emergency_stop) and self.runtime_state == RUNTIME_PLAYING:
                    self.runtime_state = RUNTIME_PAUSED  # the held move thread stays as it was
            self._step(t)

    # -- what RTDE reports -----------------------------------------------------------------------------------
    def read(self, names: list[str]) -> list:
        """Current values of output variables, in order (unknown or unsimulated names get a neutral value)."""
        with self._lock:
            t = self.now()
            self._advance(t)
            self._step(t)
            pose = self._pose.copy()
            if self.pose_noise_m > 0:
                pose[:3] += self._rng.normal(0.0, self.pose_noise_m, 3)
            pose = tuple(float(x) for x in pose)
            snapshot = self._snapshot(t, pose)
            snapshot.update(self._velocities(t))
            return [self._value(n, snapshot) for n in names]

    def safety_mode(self) -> int:
        """The safety mode now (RTDE safety_mode): a violation or fault outranks the emergency stop, which outranks
        the protective stop, which outranks the safeguard stop."""
        if self.safety_fault is not None:
            return self.safety_fault
        if self.emergency_stop:
            return SAFETY_ROBOT_EMERGENCY_STOP
        if self.protective_stop:
            return SAFETY_PROTECTIVE_STOP
        return SAFETY_SAFEGUARD_STOP if self.safeguard_stop else SAFETY_NORMAL

    def _snapshot(self, t: float, pose: tuple) -> dict:
        q = tuple(float(x) for x in inverse_kinematics(np.asarray(pose)))
        mode = self.safety_mode()
        bits = {SAFETY_ROBOT_EMERGENCY_STOP: BIT_ROBOT_ESTOP | BIT_EMERGENCY_STOPPED,
                SAFETY_PROTECTIVE_STOP: BIT_PROTECTIVE_STOPPED, SAFETY_SAFEGUARD_STOP: BIT_SAFEGUARD_STOPPED,
                SAFETY_VIOLATION: BIT_VIOLATION, SAFETY_FAULT: BIT_FAULT, SAFETY_NORMAL: BIT_NORMAL}[mode]
        if mode != SAFETY_NORMAL:
            bits |= BIT_STOPPED_DUE_TO_SAFETY
        running = self.runtime_state == RUNTIME_PLAYING
        return {
            "timestamp": t, "actual_q": q, "target_q": q, "actual_TCP_pose": pose, "target_TCP_pose": pose,
            "robot_mode": self.robot_mode, "joint_mode": (JOINT_RUNNING_MODE,) * 6,
            "safety_mode": mode, "safety_status": mode, "safety_status_bits": bits,
            "runtime_state": self.runtime_state,
            "robot_status_bits": (STATUS_POWER_ON if self.robot_mode != ROBOT_MODE_POWER_OFF else 0)
            | (STATUS_PROGRAM_RUNNING if running else 0),
            "speed_scaling": 1.0, "target_speed_fraction": self.speed_slider, "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0, "joint_temperatures": (30.0,) * 6, "actual_execution_time": 0.1,
        }

    def _velocities(self, t: float) -> dict:
        """actual_TCP_speed (linear m/s, angular rad/s, base frame) and actual_qd (rad/s) by a backward difference
        over 1 ms of the motion in progress; zero at rest."""
        m = self._motion
        tau = self._tau(t)
        if m is None or tau <= m.t_start:
            return {}
        h = min(1e-3, (tau - m.t_start) / self.speed_slider)  # controller seconds
        p1, p0 = m.pose_at(tau), m.pose_at(tau - h * self.speed_slider)
        r0 = rotvec_to_matrix(p0[3:])
        omega = r0 @ matrix_to_rotvec(r0.T @ rotvec_to_matrix(p1[3:])) / h
        speed = np.concatenate([(p1[:3] - p0[:3]) / h, omega])
        qd = (inverse_kinematics(p1) - inverse_kinematics(p0)) / h
        return {"actual_TCP_speed": tuple(map(float, speed)), "target_TCP_speed": tuple(map(float, speed)),
                "actual_qd": tuple(map(float, qd)), "target_qd": tuple(map(float, qd))}

    def _value(self, name: str, snapshot: dict):
        if name in snapshot:
            return snapshot[name]
        if name.startswith("output_int_register_"):
            return self._out_int[int(name.rsplit("_", 1)[1])]
        if name.startswith("output_double_register_"):
            return self._out_double[int(name.rsplit("_", 1)[1])]
        if name in self._inputs:
            return self._inputs[name]
        return ZERO[OUTPUT_TYPES[name]]

    def set_pose(self, pose_vec) -> None:
        """Put the arm at rest at a pose vector (6,) [m, rad] (tests)."""
        with self._lock:
            self._motion = None
            self._pose = np.asarray(pose_vec, dtype=np.float64).reshape(6).copy()
