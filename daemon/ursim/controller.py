"""State of the simulated UR controller: robot and safety modes, RTDE registers, the control script, motion.

The model is driven by three things: RTDE input packages (`write_inputs`), the script port (`start_script`) and
the fault API (`set_protective_stop`, ...). It is thread-safe (one lock) so that tests may inject faults from their
own thread while the server's event loop streams. Time is controller seconds since the model was created; motion
durations are multiplied by `time_scale` so that tests run fast.

The control script uploaded by ur_rtde is not interpreted; its register protocol is emulated instead:
`input_int_register_0` carries a command, `output_int_register_0` is 1 (ready) while the command register is 0, a
command is taken once, and `output_int_register_0` becomes 2 when it is done; `input_int_register_1` = 1 makes a move
asynchronous (done at once, `output_int_register_2` then reports the move running: bit 15, and finished).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from spadscan.daemon.arm.pose_convert import matrix_to_rotvec, rotvec_to_matrix
from spadscan.daemon.ursim.kinematics import Motion, forward_kinematics, inverse_kinematics
from spadscan.daemon.ursim.variables import OUTPUT_TYPES, ZERO

MOVE_COMMANDS = {1: "moveJ", 2: "moveJ_IK", 3: "moveL", 4: "moveL_FK"}
STOP_COMMANDS = {33: "stopL", 34: "stopJ"}
STOP_SCRIPT = 255

RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2
ROBOT_MODE_RUNNING = 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 1, 3, 7
BIT_NORMAL, BIT_PROTECTIVE_STOPPED, BIT_ROBOT_ESTOP, BIT_EMERGENCY_STOPPED = 1 << 0, 1 << 2, 1 << 6, 1 << 7
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

    def __init__(self, *, time_scale: float = 1.0, initial_pose=(0.3, 0.0, 0.3, 0.0, math.pi, 0.0)):
        self.time_scale = float(time_scale)
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self._pose = np.asarray(initial_pose, dtype=np.float64)
        self._motion: Motion | None = None
        self._motion_async = False
        self._inputs: dict[str, object] = {}
        self._out_int = [0] * 48
        self._out_double = [0.0] * 48
        self.runtime_state = RUNTIME_STOPPED
        self.protective_stop = False
        self.emergency_stop = False
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

    def _advance(self, t: float) -> None:
        """Bring the motion to time t; finish it (and signal the script) when it has arrived."""
        m = self._motion
        if m is None:
            return
        if t < m.end_time():
            self._pose = m.pose_at(t)
            return
        goal = m.goal if m.linear else forward_kinematics(m.goal)
        self._pose = np.concatenate([goal[:3], matrix_to_rotvec(rotvec_to_matrix(goal[3:]))])
        self._motion = None
        if self._motion_async:
            self._write_async(-1)
        elif self._busy:
            self._busy = False
            self._out_int[0] = 2

    def _halt(self, t: float) -> None:
        """Stop where the arm is now (stopL/stopJ, protective stop)."""
        if self._motion is not None:
            self._pose = self._motion.pose_at(t)
            self._motion = None
            if self._motion_async:
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
            self.runtime_state = RUNTIME_PLAYING
            self._busy = self._executing = False
            self._write_async(-1)
            self._out_int[0] = 1
            self._step(t)

    def write_inputs(self, values: dict[str, object]) -> None:
        """Values of one RTDE input package (name -> value); the script reacts at once."""
        with self._lock:
            self._inputs.update(values)
            t = self.now()
            self._advance(t)
            self._step(t)

    def _step(self, t: float) -> None:
        """One pass of the script's main loop (it is paused while the robot is stopped for safety)."""
        if self.runtime_state != RUNTIME_PLAYING or self._busy or self.protective_stop or self.emergency_stop:
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
        if cmd == STOP_SCRIPT:
            self._halt(t)
            self.runtime_state = RUNTIME_STOPPED
            return
        name = MOVE_COMMANDS.get(cmd) or STOP_COMMANDS.get(cmd) or f"command {cmd}"
        if cmd in MOVE_COMMANDS and not (all(map(math.isfinite, regs)) and regs[6] > 0 and regs[7] > 0):
            # A real controller raises a script error here and the program halts.
            self.errors.append(f"{name}: target {regs[:6]} speed {regs[6]} acceleration {regs[7]} rejected")
            self._halt(t)
            self.runtime_state = RUNTIME_STOPPED
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
            self._motion = Motion.plan(linear, self._pose, goal, regs[6], regs[7], t, self.time_scale)
            self._motion_async = asynchronous
            if asynchronous:
                self._write_async(0)
            else:
                self._busy = True
                self._advance(t)
                return
        elif cmd in STOP_COMMANDS:
            self._halt(t)
        self._out_int[0] = 2

    # -- faults --------------------------------------------------------------------------------------------------
    def set_protective_stop(self, on: bool) -> None:
        """Protective stop: motion halts, the script stops taking commands; clearing it aborts the halted command."""
        self._set_safety(protective=on)

    def set_emergency_stop(self, on: bool) -> None:
        """Robot emergency stop: like a protective stop, reported as safety mode 7."""
        self._set_safety(emergency=on)

    def _set_safety(self, protective: bool | None = None, emergency: bool | None = None) -> None:
        with self._lock:
            t = self.now()
            self._advance(t)
            if protective is not None:
                self.protective_stop = protective
            if emergency is not None:
                self.emergency_stop = emergency
            if self.protective_stop or self.emergency_stop:
                self._halt(t)
                self._busy = False
            self._step(t)

    # -- what RTDE reports -----------------------------------------------------------------------------------
    def read(self, names: list[str]) -> list:
        """Current values of output variables, in order (unknown or unsimulated names get a neutral value)."""
        with self._lock:
            t = self.now()
            self._advance(t)
            self._step(t)
            pose = tuple(float(x) for x in self._pose)
            snapshot = self._snapshot(t, pose)
            snapshot.update(self._velocities(t))
            return [self._value(n, snapshot) for n in names]

    def _snapshot(self, t: float, pose: tuple) -> dict:
        q = tuple(float(x) for x in inverse_kinematics(np.asarray(pose)))
        if self.emergency_stop:
            mode, bits = SAFETY_ROBOT_EMERGENCY_STOP, BIT_ROBOT_ESTOP | BIT_EMERGENCY_STOPPED
        elif self.protective_stop:
            mode, bits = SAFETY_PROTECTIVE_STOP, BIT_PROTECTIVE_STOPPED
        else:
            mode, bits = SAFETY_NORMAL, BIT_NORMAL
        running = self.runtime_state == RUNTIME_PLAYING
        return {
            "timestamp": t, "actual_q": q, "target_q": q, "actual_TCP_pose": pose, "target_TCP_pose": pose,
            "robot_mode": ROBOT_MODE_RUNNING, "joint_mode": (JOINT_RUNNING_MODE,) * 6,
            "safety_mode": mode, "safety_status": mode, "safety_status_bits": bits,
            "runtime_state": self.runtime_state,
            "robot_status_bits": STATUS_POWER_ON | (STATUS_PROGRAM_RUNNING if running else 0),
            "speed_scaling": 1.0, "target_speed_fraction": 1.0, "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0, "joint_temperatures": (30.0,) * 6, "actual_execution_time": 0.1,
        }

    def _velocities(self, t: float) -> dict:
        """actual_TCP_speed (linear m/s, angular rad/s, base frame) and actual_qd (rad/s) by a backward difference
        over 1 ms of the motion in progress; zero at rest."""
        m = self._motion
        if m is None or t <= m.t_start:
            return {}
        h = min(1e-3, t - m.t_start)
        p1, p0 = m.pose_at(t), m.pose_at(t - h)
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
