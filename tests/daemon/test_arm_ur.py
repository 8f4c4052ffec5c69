"""URArm with the real ur_rtde client (in its own process) against the simulated UR controller in a child process;
pose conversions; the link to the ur_rtde process."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from spadscan.daemon.arm.pose_convert import (matrix_to_rotvec, pose_to_vector, rotation_angle, rotvec_to_matrix,
                                              vector_to_pose)
from spadscan.daemon.arm.rtde_child import answer, ik_answered, tcp_offset_answered
from spadscan.daemon.arm.rtde_link import RTDELink
from spadscan.daemon.arm.ur import URArm, _Reading
from spadscan.daemon.devices import ArmFault, LinkLost
from spadscan.daemon.ursim.kinematics import inverse_kinematics
from spadscan.daemon.ursim.remote import SimURProcess
from spadscan.protocol.errors import ConfigError, DeviceError

_hosts = itertools.count(1)
SPEED, ACCEL = 0.5, 2.0


def _host() -> str:
    return f"127.77.{os.getpid() % 250}.{next(_hosts) % 240 + 1}"


def start_controller(time_scale: float) -> SimURProcess:
    for _ in range(10):
        try:
            return SimURProcess(_host(), time_scale=time_scale)
        except DeviceError:  # address in use: take the next one
            continue
    raise AssertionError("no free loopback address for the simulated controller")


@pytest.fixture
def ur():
    """A simulated controller process on a fresh loopback address; motion runs 10x faster than real."""
    sim = start_controller(0.1)
    yield sim
    sim.close()


@pytest.fixture
def ur_real_time():
    """A simulated controller whose moves take as long as a real arm's."""
    sim = start_controller(1.0)
    yield sim
    sim.close()


# Tests that check the arm's reported pose to 1e-6 ask the arm to arrive that closely: with the default 1 mm / 2 mm/s
# a move may end on the receive stream's sample from the cycle before the controller's "done", a few micrometres short.
EXACT = {"position_tol_m": 1e-6, "rotation_tol_rad": 1e-6}


def make_arm(host: str, **kw) -> URArm:
    # Generous timeouts, and a watchdog period the tests' own event loop keeps up with: they share two cores.
    return URArm(host, **{"frequency": 100.0, "stale_after_s": 1.0, "timeout_s": 20.0, "watchdog_hz": 1.0, **kw})


@contextlib.asynccontextmanager
async def connected_arm(host: str, **kw):
    """A connected URArm that is closed however the test ends (an unclosed one keeps reconnecting)."""
    arm = make_arm(host, **kw)
    try:
        await arm.connect()
        yield arm
    finally:
        await arm.close()


def pose(x, y, z, rot=np.eye(3)) -> np.ndarray:
    p = np.eye(4)
    p[:3, :3], p[:3, 3] = rot, (x, y, z)
    return p


DOWN = np.diag([1.0, -1.0, -1.0])  # tool z pointing down: pi about x
DIAG_PI = 2.0 * np.outer([1, 1, 0], [1, 1, 0]) / 2.0 - np.eye(3)  # pi about (1, 1, 0) / sqrt 2
NEAR_PI = rotvec_to_matrix(np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]) * (math.pi - 1e-9))
TILTED = rotvec_to_matrix([0.2, 2.9, -0.1])


async def wait_for_moves(ur, n: int, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while len(ur.moves) < n:
        assert time.monotonic() < deadline, f"the controller never took command {n}"
        await asyncio.sleep(0.01)


def test_moves_arrive_at_the_commanded_poses_and_state_reports_the_actual_pose(ur, arun):
    targets = [pose(0.4, 0.1, 0.3, DOWN), pose(0.35, -0.1, 0.25, NEAR_PI), pose(0.3, 0.05, 0.35, DIAG_PI),
               pose(0.45, 0.0, 0.2, TILTED), pose(0.3, 0.0, 0.3, rotvec_to_matrix([1e-8, 0.0, 0.0]))]

    async def scan():
        async with connected_arm(ur.host, **EXACT) as arm:
            await arm.prepare()
            states = []
            for target in targets:
                await arm.move_to(target, SPEED, ACCEL)
                states.append(await arm.state())
            controller_pose = ur.pose()
        return states, controller_pose

    states, controller_pose = arun(scan())
    for target, state in zip(targets, states):
        assert np.allclose(state.tcp_pose, target, atol=1e-6)
        assert state.joints.shape == (6,) and not state.protective_stop
    assert np.allclose(states[-1].joints, inverse_kinematics(np.array(controller_pose)), atol=1e-9)
    assert states[-1].timestamp_s > states[0].timestamp_s
    moves = ur.moves
    assert [m.name for m in moves] == ["moveL"] * len(targets)
    for target, move in zip(targets, moves):
        assert np.allclose(move.target[:3], target[:3, 3], atol=1e-6)
        assert rotation_angle(rotvec_to_matrix(move.target[3:]), target[:3, :3]) < 1e-6
        assert (move.speed, move.accel) == (SPEED, ACCEL)


async def cleared(arm) -> None:
    """Until the arm's own reading shows the stop cleared: the receive stream may still hold a package from before
    the clear, and a move sent at once would be refused on it (an operator's `ctl resume` comes seconds later)."""
    deadline = time.monotonic() + 60
    while (await arm.state()).protective_stop:
        assert time.monotonic() < deadline, "the arm never reported the stop cleared"
        await asyncio.sleep(0.01)


def test_protective_stop_refuses_the_move(ur, arun):
    async def run():
        async with connected_arm(ur.host) as arm:
            await arm.move_to(pose(0.4, 0.0, 0.3, DOWN))
            ur.protective_stop()
            with pytest.raises(ArmFault, match="protective stop"):
                await asyncio.wait_for(arm.move_to(pose(0.4, 0.1, 0.3, DOWN)), 30)
            stopped = (await arm.state()).protective_stop
            with pytest.raises(ArmFault, match="protective stop"):
                await arm.prepare()
            ur.clear_protective_stop()
            await cleared(arm)
            await arm.clear_fault()  # the runner's step on resume (a watchdog starved on a busy machine is re-armed)
            await arm.move_to(pose(0.4, 0.2, 0.3, DOWN))
            after = (await arm.state()).protective_stop
        return stopped, after

    assert arun(run()) == (True, False)
    assert [m.target[1] for m in ur.moves] == [0.0, 0.2]  # the refused move never reached the controller


class ArmWithoutPreCheck(URArm):
    """Sends a move even when its own last reading shows a stop, as when the stop comes between check and send."""

    async def _raise_if_stopped(self, reading, doing):
        if doing != "moveL refused":
            await super()._raise_if_stopped(reading, doing)


def test_move_returning_false_is_explained_by_the_protective_stop(ur, arun):
    async def run():
        arm = ArmWithoutPreCheck(ur.host, frequency=100.0, stale_after_s=1.0, timeout_s=20.0, watchdog_hz=1.0)
        try:
            await arm.connect()
            ur.protective_stop()
            with pytest.raises(ArmFault, match="protective stop.*refused"):
                await asyncio.wait_for(arm.move_to(pose(0.4, 0.1, 0.3, DOWN)), 30)
        finally:
            await arm.close()

    arun(run())
    assert ur.moves == []


class LaggingReceive(URArm):
    """Its receive stream shows a safety stop only `lag` readings after the control stream shows the script
    stopped (two RTDE connections: either can be behind)."""

    def __init__(self, lag: int, flag: bool = True):
        super().__init__("127.0.0.1")
        self.lag, self.flag, self.reads = lag, flag, 0

    async def _fresh(self, what):
        self.reads += 1
        return reading(program_running=False, protective=self.flag and self.reads >= self.lag)


def reading(**kw) -> _Reading:
    return _Reading(**{"pose_vec": np.zeros(6), "joints": np.zeros(6), "timestamp": 1.0, "protective": False,
                       "emergency": False, "safety_mode": 1, "connected": True, "tcp_speed": np.zeros(6), **kw})


def test_a_script_stopped_by_a_protective_stop_is_named_by_the_stop_when_the_receive_stream_lags(arun):
    arm = LaggingReceive(lag=3)
    with pytest.raises(ArmFault, match="protective stop on .*moveL aborted"):
        arun(arm._raise_if_stopped(reading(program_running=False), "moveL aborted"))
    assert arm.reads == 3
    alone = LaggingReceive(lag=0, flag=False)  # no safety stop shows: the script stopped by itself
    with pytest.raises(ArmFault, match="control script is not running"):
        arun(alone._raise_if_stopped(reading(program_running=False), "moveL aborted"))
    assert alone.reads >= 1
    running = LaggingReceive(lag=1)
    arun(running._raise_if_stopped(reading(), "moveL aborted"))  # nothing wrong: not read again
    assert running.reads == 0


class RefusingController(URArm):
    """Refuses the first planned pose; its receive stream shows a protective stop from the `stop_at`-th reading on
    (None: never), the script running until then."""

    def __init__(self, stop_at: int | None):
        super().__init__("127.0.0.1")
        self._open, self.stop_at, self.reads = True, stop_at, 0

    async def _call(self, what, method, *args, timeout_s=None):
        if method == "program_running":
            return self.stop_at is None
        if method == "tcp_offset":  # the bare flange
            return [0.0] * 6
        assert method == "check_poses"
        return {"index": 0, "check": "safety", "ik_checked": False}

    async def _fresh(self, what):
        self.reads += 1
        stopped = self.stop_at is not None and self.reads >= self.stop_at
        await asyncio.sleep(0.002)  # a reading every 2 ms, as the controller's 500 Hz stream
        return reading(program_running=not stopped, protective=stopped)


def test_a_pose_refused_by_a_controller_that_just_stopped_for_safety_is_named_by_the_stop(arun):
    # The stop shows in the receive stream after the refusal: first the check before the queries, then the refusal,
    # then a few readings later the stop.
    late = RefusingController(stop_at=5)
    with pytest.raises(ArmFault, match="protective stop on .*cannot check the planned poses"):
        arun(late.check_poses(np.eye(4)[None]))
    refused = RefusingController(stop_at=None)  # nothing shows: the pose itself is refused
    with pytest.raises(ArmFault, match=r"pose 0 of 1: TCP at .* outside the controller's safety limits"):
        arun(refused.check_poses(np.eye(4)[None]))
    assert refused.reads > 5, "the safety state was read again before the pose was blamed"


def test_a_move_refused_for_good_by_a_controller_that_just_stopped_for_safety_is_named_by_the_stop(arun):
    # As for the pose checks: the stop shows a few readings after the second refusal of the move.
    late = RefusingController(stop_at=5)
    with pytest.raises(ArmFault, match="protective stop on .*moveL to .* refused"):
        arun(late._explain_refusal("moveL to [0.3000, 0.0000, 0.2000] m", final=True))
    refused = RefusingController(stop_at=None)
    with pytest.raises(ArmFault, match=r"controller refused moveL to .* control script running"):
        arun(refused._explain_refusal("moveL to [0.3000, 0.0000, 0.2000] m", final=True))
    assert refused.reads > 5, "the safety state was read again before the move was blamed"


@pytest.mark.parametrize("kind", ["protective", "emergency"])
def test_a_safety_stop_during_a_move_aborts_it_at_once(ur, arun, kind):
    """The controller halts the arm and leaves the move "running" (ur_rtde's script writes "finished" only when the
    move ends or is killed): the arm sees the stop in the safety state while it polls the move, and says so at once
    instead of waiting out the move's time budget."""
    async def run():
        async with connected_arm(ur.host) as arm:
            move = asyncio.ensure_future(arm.move_to(pose(0.3, 0.2, 0.3, DOWN), 0.005, 1.0))  # 40 s scaled to 4 s
            await wait_for_moves(ur, 1)
            await until(lambda: ur.state()["moving"], "the move to run")
            t0 = time.monotonic()
            getattr(ur, f"{kind}_stop")()
            with pytest.raises(ArmFault, match=f"{kind} stop.*aborted"):
                await asyncio.wait_for(move, 30)
            took = time.monotonic() - t0
            state = await arm.state()
        return took, state, ur.state()["moving"]

    took, state, still_running = arun(run())
    assert took < 5.0, f"the stop was reported {took:.1f} s after it came"
    assert still_running  # the controller's view: the halted move was never reported finished
    assert state.protective_stop and state.safety_stop == f"{kind} stop"
    assert state.tcp_pose[1, 3] < 0.19  # halted on the way


@pytest.mark.parametrize("kind", ["protective", "safeguard", "emergency"])
def test_the_state_names_the_safety_stop_that_holds_the_arm(ur, arun, kind):
    """At rest (the arm standing at a pose while the sensor captures): the state says which stop it is, so that the
    pause names it (each is cleared differently); once cleared, none."""
    async def run():
        async with connected_arm(ur.host) as arm:
            free = await arm.state()
            getattr(ur, f"{kind}_stop")()
            async with asyncio.timeout(30):
                while not (held := await arm.state()).protective_stop:  # until the receive stream shows it
                    await asyncio.sleep(0.01)
            getattr(ur, f"clear_{kind}_stop")()
            await cleared(arm)
            return free, held, await arm.state()

    free, held, after = arun(run())
    assert (free.safety_stop, held.safety_stop, after.safety_stop) == (None, f"{kind} stop", None)


def test_emergency_stop_is_an_arm_fault(ur, arun):
    async def run():
        async with connected_arm(ur.host) as arm:
            ur.emergency_stop()
            with pytest.raises(ArmFault, match="emergency stop"):
                await asyncio.wait_for(arm.move_to(pose(0.4, 0.0, 0.3, DOWN)), 30)

    arun(run())
    assert ur.moves == []


@pytest.mark.parametrize("kind, mode", [("violation", 8), ("fault", 9)])
def test_a_safety_violation_or_fault_names_its_mode_and_says_to_restart_the_arm(ur, arun, kind, mode):
    """Safety mode 8 or 9 (RTDE guide): the safety system stopped the arm, and the controller the program. The move
    in progress is reported at once by that mode, with UR's remedy (restart the arm from the pendant), not as a
    control script the watchdog stopped that resuming uploads again. A resume before the restart uploads nothing
    (no program runs until then) and the next move says the same. The arm comes back from the restart powered off
    (robot mode 3, then 5 once powered, its brakes on): a resume then says so, by the robot mode, and uploads
    nothing (the script would not start, and ur_rtde's connection would give up on it as a lost link); once it is
    powered on and its brakes released, moves work again."""
    async def run():
        async with connected_arm(ur.host) as arm:
            move = asyncio.ensure_future(arm.move_to(pose(0.3, 0.2, 0.3, DOWN), 0.005, 1.0))  # 4 s scaled
            await wait_for_moves(ur, 1)
            await until(lambda: ur.state()["moving"], "the move to run")
            ur.safety_fault(kind)
            with pytest.raises(ArmFault) as aborted:
                await asyncio.wait_for(move, 30)
            held, scripts = await arm.state(), ur.scripts()
            await arm.clear_fault()  # the operator resumed without restarting the arm
            with pytest.raises(ArmFault) as again:
                await arm.move_to(pose(0.35, 0.0, 0.3, DOWN))
            uploaded_while_held = ur.scripts() - scripts
            ur.restart_safety()
            await cleared(arm)
            unready = []
            for ready in (ur.power_on, ur.release_brakes):
                with pytest.raises(ArmFault) as unpowered:
                    await arm.clear_fault()
                unready.append(str(unpowered.value))
                ready()
            uploaded_unpowered = ur.scripts() - scripts
            await arm.clear_fault()
            await arm.move_to(pose(0.35, 0.0, 0.3, DOWN))
            return (aborted.value, again.value, held, uploaded_while_held, ur.scripts() - scripts, ur.state(), unready,
                    uploaded_unpowered)

    aborted, again, held, uploaded_while_held, uploaded, after, unready, uploaded_unpowered = arun(run())
    advice = "power it on and release the brakes on the teach pendant, then resume"
    assert [line.split(": ", 1)[1] for line in unready] == [
        f"the arm is powered off (robot mode 3): {advice}",
        f"the arm is powered on with its brakes on (robot mode 5): {advice}"], unready
    assert uploaded_unpowered == 0
    restart = (r"restart the arm from the pendant \(its safety system must be restarted after a " + kind
               + r"; the arm comes back powered off: power it on and release the brakes\), then resume\)$")
    assert re.match(rf"safety {kind} on UR arm .*: moveL to .* aborted \(safety mode {mode} \({kind}\); .*{restart}",
                    str(aborted)), str(aborted)
    assert re.match(rf"safety {kind} on UR arm .*: moveL refused \(safety mode {mode} \({kind}\); .*{restart}",
                    str(again)), str(again)
    assert "control script is not running" not in str(aborted) + str(again)
    assert held.safety_stop == f"safety {kind}" and held.protective_stop
    assert uploaded_while_held == 0 and uploaded == 1
    assert after["safety_mode"] == 1 and after["runtime_state"] == 2 and after["watchdog_period_s"] == 1.0
    assert [m.name for m in ur.moves] == ["moveL", "moveL"]


def test_connecting_to_an_arm_that_runs_no_program_says_to_power_it_on(ur, arun):
    """An arm restarted after a safety fault and left powered off: ur_rtde's connection uploads its script, which
    does not start, and gives up after 5 s. The connect says why, by the robot mode, as an arm fault (the operator's
    to clear, not a lost link); once the arm is powered on and its brakes released, it connects."""
    ur.safety_fault("fault")
    ur.restart_safety()

    async def run():
        arm = make_arm(ur.host)
        try:
            with pytest.raises(ArmFault) as unpowered:
                await arm.connect()
            ur.power_on()
            ur.release_brakes()
            await arm.connect()
            await arm.move_to(pose(0.35, 0.0, 0.3, DOWN))
        finally:
            await arm.close()
        return unpowered.value

    unpowered = arun(run())
    assert str(unpowered).endswith(": the arm is powered off (robot mode 3): power it on and release the brakes on "
                                   "the teach pendant, then resume"), str(unpowered)
    assert [m.name for m in ur.moves] == ["moveL"]


class StoppedScript(URArm):
    """Its control script is not running, in safety mode `mode`, and no safety stop shows."""

    def __init__(self, mode: int):
        super().__init__("127.0.0.1")
        self.mode = mode

    async def _fresh(self, what):
        return reading(program_running=False, safety_mode=self.mode)


def test_a_control_script_that_is_not_running_is_reported_with_the_safety_mode_by_name(arun):
    recovering = StoppedScript(4)
    with pytest.raises(ArmFault, match=r"control script is not running on the controller \(safety mode 4 "
                                       r"\(recovery\); the watchdog stops it"):
        arun(recovering._raise_if_stopped(reading(program_running=False, safety_mode=4), "moveL aborted"))
    for bits, name in ((1 << 8, "safety violation"), (1 << 9, "safety fault")):  # the bit alone names it too
        assert reading(safety_bits=bits).stop == name


def test_cancelled_move_stops_the_arm(ur, arun):
    async def run():
        async with connected_arm(ur.host) as arm:
            move = asyncio.ensure_future(arm.move_to(pose(0.3, 0.2, 0.3, DOWN), 0.005, 1.0))
            await wait_for_moves(ur, 1)
            move.cancel()
            with pytest.raises(asyncio.CancelledError):
                await move
            await wait_for_moves(ur, 2)

    arun(run())
    assert [m.name for m in ur.moves] == ["moveL", "stopL"]
    assert ur.pose()[1] < 0.19


@pytest.mark.parametrize("mode", ["silent", "freeze", "close"])
def test_dropped_link_is_link_lost_and_reconnect_works(ur, arun, mode):
    async def run():
        async with connected_arm(ur.host, **EXACT) as arm:
            await arm.move_to(pose(0.4, 0.0, 0.3, DOWN))
            ur.drop_link(mode)
            deadline = time.monotonic() + 30
            with pytest.raises(LinkLost) as lost:
                while time.monotonic() < deadline:
                    await arm.state()
                    await asyncio.sleep(0.05)
            with pytest.raises(LinkLost):
                await asyncio.wait_for(arm.move_to(pose(0.4, 0.1, 0.3, DOWN)), 30)
            with pytest.raises(LinkLost):
                await asyncio.wait_for(arm.release(), 30)
            rtde_before = ur.connections()["rtde"]
            ur.restore_link()
            await arm.connect()
            await arm.move_to(pose(0.4, 0.2, 0.3, DOWN))
            state = await arm.state()
        return str(lost.value), state, ur.connections()["rtde"] - rtde_before

    message, state, new_sessions = arun(run())
    assert ur.host in message
    assert ("closed" if mode == "close" else "stale") in message
    assert np.allclose(state.tcp_pose, pose(0.4, 0.2, 0.3, DOWN), atol=1e-6)
    assert [m.target[1] for m in ur.moves if m.name == "moveL"] == [0.0, 0.2]
    if mode == "freeze":  # commands still get through a frozen data stream: the stopL sent before dropping it did
        assert [m.name for m in ur.moves] == ["moveL", "stopL", "moveL"]
    if mode == "close":
        assert new_sessions == 2  # reconnecting built new receive and control interfaces


async def until(pred, what: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.02)


def test_a_silent_daemon_is_stopped_by_the_controllers_watchdog(ur, arun):
    """The daemon's event loop stops (a debugger, SIGSTOP, a hang) in the middle of a long move: the controller's
    watchdog (setWatchdog) sees no kick for a whole period, stops the program and with it the arm, far short of the
    target. The next move says why; resuming uploads the script again and moves work."""
    async def run():
        async with connected_arm(ur.host) as arm:  # the file's 1 Hz watchdog: a busy machine's loop keeps up
            await arm.prepare()
            move = asyncio.ensure_future(arm.move_to(pose(0.3, 0.2, 0.3, DOWN), 0.005, 1.0))  # 4 s scaled
            await wait_for_moves(ur, 1)
            time.sleep(3.0)  # the whole event loop stands still: no kick leaves
            with pytest.raises(ArmFault, match="control script is not running"):
                await asyncio.wait_for(move, 30)
            stopped, where = ur.state(), ur.pose()
            await asyncio.sleep(1.0)
            still = ur.pose()
            scripts = ur.scripts()
            await arm.clear_fault()
            await arm.move_to(pose(0.35, 0.0, 0.3, DOWN))
            return stopped, where, still, scripts, ur.scripts(), ur.state()

    stopped, where, still, scripts, scripts_after, after = arun(run())
    assert stopped["watchdog_stops"] == 1 and stopped["runtime_state"] == 1
    assert where[1] < 0.15 and still == where  # halted on the way, and stays there
    assert scripts_after == scripts + 1 and after["runtime_state"] == 2 and after["watchdog_period_s"] == 1.0


def test_a_kicked_watchdog_never_stops_a_daemon_that_waits(ur, arun):
    """A paused scan sends no command for a long time; the kicks keep the program running."""
    async def run():
        async with connected_arm(ur.host, watchdog_hz=1.0) as arm:
            await arm.prepare()
            await asyncio.sleep(4.0)
            await arm.move_to(pose(0.35, 0.0, 0.3, DOWN))
            return ur.state()

    state = arun(run())
    assert state["watchdog_stops"] == 0 and state["watchdog_period_s"] == 1.0


def test_a_lost_link_gets_a_stop_before_it_is_dropped(ur, arun):
    """The data stream freezes mid-move (a hung controller connection): before ending the client, the arm sends
    stopL, which the controller still takes, so the move it can no longer watch stops at once."""
    async def run():
        async with connected_arm(ur.host) as arm:
            move = asyncio.ensure_future(arm.move_to(pose(0.3, 0.2, 0.3, DOWN), 0.005, 1.0))  # 4 s scaled
            await wait_for_moves(ur, 1)
            # Frozen while the script shows "done" (before the client cleared the move), no command could be sent.
            await until(lambda: ur.state()["script_state"] == 1, "the client to clear the move command")
            ur.drop_link("freeze")  # the stream then repeats the state at this moment
            with pytest.raises(LinkLost, match="stale"):
                await asyncio.wait_for(move, 30)
            ur.restore_link()
            return ur.moves, ur.state(), ur.pose()

    moves, state, where = arun(run())
    assert [m.name for m in moves] == ["moveL", "stopL"]
    assert not state["moving"] and where[1] < 0.19


def test_a_safeguard_stop_is_an_arm_fault_like_a_protective_stop(ur, arun):
    """Safety mode 5, safety_status_bits bit 4 (a light curtain, a door): the move in progress is reported at once
    with that reason, nothing moves until it is reset."""
    async def run():
        async with connected_arm(ur.host) as arm:
            move = asyncio.ensure_future(arm.move_to(pose(0.3, 0.2, 0.3, DOWN), 0.005, 1.0))  # 4 s scaled
            await wait_for_moves(ur, 1)
            t0 = time.monotonic()
            ur.safeguard_stop()
            with pytest.raises(ArmFault, match=r"safeguard stop on .*aborted \(safety mode 5 \(safeguard stop\)"):
                await asyncio.wait_for(move, 30)
            took = time.monotonic() - t0
            stopped = (await arm.state()).protective_stop
            with pytest.raises(ArmFault, match="safeguard stop"):
                await arm.prepare()
            with pytest.raises(ArmFault, match="safeguard stop"):
                await arm.move_to(pose(0.35, 0.0, 0.3, DOWN))
            ur.clear_safeguard_stop()
            await cleared(arm)
            await arm.clear_fault()  # the runner's step on resume (a watchdog starved on a busy machine is re-armed)
            await arm.move_to(pose(0.35, 0.0, 0.3, DOWN))
            return took, stopped, (await arm.state()).protective_stop

    took, stopped, after = arun(run())  # the match above: the stop aborted the move, not its time budget
    # At once, from the safety state: the controller leaves the halted move "running" (as ur_rtde's script does), so
    # only the check while the move is polled sees the stop, not a wait for the move's end (its budget is ~100 s).
    assert took < 5.0, f"the stop was reported {took:.1f} s after it came"
    assert stopped and not after
    assert [m.name for m in ur.moves] == ["moveL", "moveL"]


def test_a_control_script_paused_by_a_protective_stop_is_uploaded_again_on_resume(ur, arun):
    """A protective stop pauses the program, as on a real controller; it stays paused once the stop is cleared, and
    ur_rtde refuses every command ("RTDE control script is not running": its isProgramRunning is runtime_state ==
    PLAYING). The arm says so; clear_fault (the runner's step on resume) uploads the script again, and moves work."""

    async def run():
        async with connected_arm(ur.host, **EXACT) as arm:
            await arm.move_to(pose(0.35, 0.0, 0.3, DOWN))
            ur.protective_stop()
            ur.clear_protective_stop()
            await cleared(arm)
            paused = ur.state()["runtime_state"]
            with pytest.raises(ArmFault, match="control script is not running"):
                await arm.move_to(pose(0.35, 0.1, 0.3, DOWN))
            scripts = ur.scripts()
            await arm.clear_fault()
            await arm.move_to(pose(0.35, 0.1, 0.3, DOWN))
            return paused, scripts, ur.scripts(), await arm.state()

    paused, scripts, after, state = arun(run())
    assert paused == 4 and after == scripts + 1
    assert np.allclose(state.tcp_pose, pose(0.35, 0.1, 0.3, DOWN), atol=1e-6)
    assert [m.target[1] for m in ur.moves] == [0.0, 0.1]


def test_the_controller_is_asked_about_every_planned_pose(ur, arun):
    """isPoseWithinSafetyLimits and getInverseKinematicsHasSolution for each pose; the first refused is named."""
    ur.configure(safety_floor_z=0.1)
    ok = [pose(0.35, 0.0, 0.3, DOWN), pose(0.3, 0.1, 0.25, DOWN)]

    async def run():
        async with connected_arm(ur.host) as arm:
            await arm.check_poses(np.stack(ok))
            asked = ur.state()["queries"]
            with pytest.raises(ArmFault, match=r"pose 5 of 6: TCP at \[0.300, 0.000, 0.050\] m is outside the "
                                               r"controller's safety limits"):
                await arm.check_poses(np.stack([*ok, pose(0.3, 0.0, 0.05, DOWN)]), first_index=3)
            with pytest.raises(ArmFault, match="pose 0 of 1: .* outside the controller's safety limits"):
                await arm.check_poses(pose(1.5, 0.0, 0.3, DOWN)[None])  # beyond its reach
        return asked

    asked = arun(run())
    assert [q[0] for q in asked] == ["within_safety_limits", "has_ik_solution"] * 2 and all(q[2] for q in asked)
    np.testing.assert_allclose(asked[2][1][:3], [0.3, 0.1, 0.25])
    assert ur.moves == []


POINTER = (0.0, 0.0, 0.1, 0.0, 0.0, 0.5)  # a 100 mm pointer on the tool axis, turned 28.65 deg about it


def test_a_tcp_offset_left_active_on_the_pendant_refuses_the_arm_before_anything_moves(ur, arun):
    """A "pointer" TCP left active after measuring a calibration target: ur_rtde's getTCPOffset (command 40, answered
    in output_double_register_0..5) reads it at connect, and the arm refuses in one line naming it; no command that
    moves is sent, and a move asked for all the same is refused again. Back on the bare flange, a new connection
    (a new program takes the installation's TCP) moves."""
    ur.configure(tcp_offset=POINTER)
    start = ur.pose()

    async def run():
        arm = make_arm(ur.host)
        try:
            with pytest.raises(ArmFault) as refused:
                await arm.connect()
            with pytest.raises(ArmFault, match="active TCP offset"):
                await arm.move_to(pose(0.4, 0.0, 0.3, DOWN))
            offset = arm.tcp_offset
            moves_refused, pose_refused = ur.moves, ur.pose()
            ur.configure(tcp_offset=(0.0,) * 6)
            await arm.reconnect()
            await arm.prepare()
            await arm.move_to(pose(0.4, 0.0, 0.3, DOWN))
            return str(refused.value), offset, moves_refused, pose_refused, arm.tcp_offset
        finally:
            await arm.close()

    message, offset, moves_refused, pose_refused, offset_after = arun(run())
    assert "\n" not in message
    assert "active TCP offset is [0.0, 0.0, 100.0] mm, [0.00, 0.00, 28.65] deg" in message, message
    assert "select the bare-flange TCP on the teach pendant" in message and "set its offset to zero" in message
    assert offset == pytest.approx(POINTER) and offset_after == [0.0] * 6
    assert moves_refused == [] and pose_refused == pytest.approx(start)  # nothing moved, nothing was even stopped
    assert [m.name for m in ur.moves] == ["moveL"]
    assert ur.state()["tcp_offset_reads"] == 3  # at connect, before the refused move, after reconnecting


@pytest.mark.parametrize("offset", [(0.0,) * 6, (5e-5, 0.0, -5e-5, 0.0, 5e-4, 0.0)])
def test_the_bare_flange_tcp_connects_as_before(ur, offset, arun):
    """A zero TCP offset (or one within 0.1 mm / 1 mrad of it) is the bare flange: read once at connect, recorded,
    and the arm prepares and moves as before."""
    ur.configure(tcp_offset=offset)

    async def run():
        async with connected_arm(ur.host) as arm:
            read = arm.tcp_offset
            await arm.prepare()
            await arm.move_to(pose(0.4, 0.0, 0.3, DOWN))
        return read

    assert arun(run()) == pytest.approx(offset)
    assert [m.name for m in ur.moves] == ["moveL"] and ur.state()["tcp_offset_reads"] == 1


def test_a_tcp_offset_the_stopped_controller_cannot_report_at_connect_is_read_before_the_first_move(ur, arun):
    """A protective stop at connect: the script answers nothing, so connecting does not ask; the stop refuses the
    preparation, and once it is cleared the offset is read before the first move, which it refuses."""
    ur.configure(tcp_offset=POINTER)
    ur.protective_stop()

    async def run():
        async with connected_arm(ur.host) as arm:
            with pytest.raises(ArmFault, match="protective stop"):
                await arm.prepare()
            reads = ur.state()["tcp_offset_reads"]
            ur.clear_protective_stop()
            await cleared(arm)
            with pytest.raises(ArmFault, match=r"active TCP offset is \[0.0, 0.0, 100.0\] mm"):
                await arm.move_to(pose(0.4, 0.0, 0.3, DOWN))
        return reads

    assert arun(run()) == 0
    assert ur.moves == [] and ur.state()["tcp_offset_reads"] == 1


def test_a_slowed_speed_slider_is_not_a_stuck_move(ur_real_time, arun):
    """The pendant's speed slider at 8 %: a 0.6 s move takes 7.5 s. Its time budget (twice the planned time plus
    timeout_s: 5.2 s) counts motion time at the controller's speed scaling, so the move ends normally."""
    ur = ur_real_time

    async def run():
        async with connected_arm(ur.host, timeout_s=4.0, **EXACT) as arm:
            await arm.move_to(pose(0.3, 0.0, 0.3, DOWN), 0.2, 2.0)
            ur.configure(speed_slider=0.08)
            t0 = time.monotonic()
            await arm.move_to(pose(0.3, 0.1, 0.3, DOWN), 0.2, 2.0)
            return time.monotonic() - t0, await arm.state()

    took, state = arun(run())
    assert took > 6.0
    assert np.allclose(state.tcp_pose, pose(0.3, 0.1, 0.3, DOWN), atol=1e-6)


def test_the_speed_slider_is_read_afresh_without_a_move(ur, arun):
    """`read_speed_slider` (what `ctl status` asks while a scan is paused) reads the pendant's slider as it is now,
    and notes when; nothing moves."""

    async def run():
        async with connected_arm(ur.host) as arm:
            ur.configure(speed_slider=0.3)
            t0 = time.monotonic()
            while arm.speed_slider != 0.3:  # the receive stream comes at the controller's own pace
                assert time.monotonic() - t0 < 20.0, f"the slider read {arm.speed_slider}"
                await arm.read_speed_slider()
                await asyncio.sleep(0.01)
            return arm.speed_slider_at - t0

    assert arun(run()) >= 0.0
    assert ur.moves == []


def test_a_move_whose_thread_reports_running_late_is_waited_for_to_its_end(ur, arun):
    """ur_rtde's control script answers an asynchronous moveL at once and reports the move running only when its
    thread runs (here 0.3 s later): a long move (2 s, longer than timeout_s) is not taken for one already over."""
    ur.configure(move_thread_start_s=0.3)

    async def run():
        async with connected_arm(ur.host, timeout_s=1.0, **EXACT) as arm:
            await arm.move_to(pose(0.3, 0.0, 0.3, DOWN), 0.2, 2.0)
            await arm.move_to(pose(0.3, 0.2, 0.3, DOWN), 0.01, 2.0)  # 20 s of motion, 2 s at the sim's rate
            return await arm.state()

    state = arun(run())
    assert np.allclose(state.tcp_pose, pose(0.3, 0.2, 0.3, DOWN), atol=1e-6)


def test_moves_arrive_within_tolerance_of_a_noisy_actual_pose(ur, arun):
    """A real controller's actual pose scatters (here 0.2 mm per axis): moves arrive within the 1 mm tolerance, and
    the state reports the scattered actual pose, not the target."""
    ur.configure(pose_noise_m=2e-4)

    async def run():
        async with connected_arm(ur.host) as arm:
            out = []
            for y in (0.0, 0.05, 0.1):
                await arm.move_to(pose(0.35, y, 0.3, DOWN))
                out.append((await arm.state()).tcp_pose[:3, 3] - [0.35, y, 0.3])
            return np.array(out)

    off = np.linalg.norm(arun(run()), axis=1)
    assert np.all(off > 0) and np.all(off < 2e-3)


def _alive(pid: int) -> bool:
    """Whether a process exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _fds() -> int:
    return len(os.listdir(f"/proc/{os.getpid()}/fd"))


def test_close_ends_the_ur_rtde_process_and_leaves_nothing_open(ur, arun):
    fds = _fds()

    async def run():
        async with connected_arm(ur.host) as arm:
            await arm.move_to(pose(0.4, 0.0, 0.3, DOWN))
            pid = arm._link.pid
            busy = _alive(pid) and ur.open_connections() > 0
            await arm.release()
            await arm.close()
        await arm.release()  # closed: nothing to do
        return pid, busy

    pid, busy = arun(run())
    assert busy and not _alive(pid)
    assert [m.name for m in ur.moves] == ["moveL", "stopL"]
    assert _fds() == fds
    deadline = time.monotonic() + 20
    while ur.open_connections() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert ur.open_connections() == 0


def test_a_crash_of_ur_rtde_is_a_lost_link_and_reconnect_recovers(ur, arun):
    """ur_rtde dies (as it does when its own reconnect races a returning link): the arm reports the lost link with the
    signal, later calls fail at once, and connect() starts a fresh client that works."""
    async def run():
        async with connected_arm(ur.host, **EXACT) as arm:
            await arm.move_to(pose(0.4, 0.0, 0.3, DOWN))
            os.kill(arm._link.pid, signal.SIGSEGV)
            with pytest.raises(LinkLost) as lost:
                for _ in range(200):
                    await arm.state()
                    await asyncio.sleep(0.01)
            with pytest.raises(LinkLost, match="reconnect first"):
                await arm.move_to(pose(0.4, 0.1, 0.3, DOWN))
            await arm.connect()
            await arm.move_to(pose(0.4, 0.2, 0.3, DOWN))
            return str(lost.value), await arm.state()

    message, state = arun(run())
    assert "SIGSEGV" in message and ur.host in message
    assert np.allclose(state.tcp_pose, pose(0.4, 0.2, 0.3, DOWN), atol=1e-6)
    assert [m.target[1] for m in ur.moves] == [0.0, 0.2]


def test_a_link_that_comes_back_at_once_never_takes_the_daemon_down(ur, arun):
    """The controller closes every connection and takes them again at once: ur_rtde 1.6.5's control interface then
    reconnects by itself from two threads, which crashes its process about one time in four within 2 s (this crashed
    the daemon's process when ur_rtde ran in it). Here the arm reports a lost link (SIGSEGV or a closed link), or
    nothing at all, and works after connect()."""
    async def run():
        async with connected_arm(ur.host, **EXACT) as arm:
            await arm.move_to(pose(0.4, 0.0, 0.3, DOWN))
            ur.drop_link("close")
            ur.restore_link()
            await asyncio.sleep(2.0)  # no call meanwhile: ur_rtde's reconnect threads race undisturbed
            with contextlib.suppress(LinkLost):
                await arm.state()
            await arm.connect()
            await arm.move_to(pose(0.4, 0.2, 0.3, DOWN))
            return await arm.state()

    for _ in range(3):
        state = arun(run())
        assert np.allclose(state.tcp_pose, pose(0.4, 0.2, 0.3, DOWN), atol=1e-6)


def test_arguments_are_checked_before_anything_moves(arun):
    for kwargs in ({"speed": 0.0}, {"speed": 4.0}, {"accel": -1.0}, {"stale_after_s": math.nan},
                   {"frequency": 0.0}, {"timeout_s": 0.0}):
        with pytest.raises(ConfigError):
            URArm("127.0.0.1", **kwargs)
    with pytest.raises(ConfigError):
        URArm("")

    async def run():
        arm = URArm(f"127.77.{os.getpid() % 250}.250", timeout_s=10.0)
        with pytest.raises(ArmFault, match="speed"):
            await arm.move_to(pose(0.4, 0.0, 0.3, DOWN), speed=5.0)
        with pytest.raises(ArmFault, match="rotation"):
            await arm.move_to(pose(0.4, 0.0, 0.3, 1.01 * DOWN))
        with pytest.raises(ArmFault, match="4x4"):
            await arm.move_to(np.eye(3))
        with pytest.raises(LinkLost, match="not connected"):
            await arm.move_to(pose(0.4, 0.0, 0.3, DOWN))
        with pytest.raises(LinkLost, match="127.77"):
            await arm.connect()  # nothing listens there
        assert arm._link is None  # the failed connect left no ur_rtde process behind
        await arm.close()

    arun(run())


def test_rotation_vectors_of_known_rotations():
    assert np.allclose(rotvec_to_matrix([0.0, 0.0, math.pi / 2]), [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert np.allclose(np.abs(matrix_to_rotvec(DOWN)), [math.pi, 0, 0])
    assert np.allclose(np.abs(matrix_to_rotvec(DIAG_PI)), [math.pi / math.sqrt(2)] * 2 + [0])
    assert np.allclose(matrix_to_rotvec(np.eye(3)), 0)
    assert np.allclose(pose_to_vector(pose(1, 2, 3, rotvec_to_matrix([0.1, 0.2, 0.3]))), [1, 2, 3, 0.1, 0.2, 0.3])


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-6, 0.5, 3.0, math.pi - 1e-6, math.pi - 1e-12, math.pi])
def test_pose_vector_round_trip_is_exact_near_zero_and_pi(angle):
    rng = np.random.default_rng(1)
    for _ in range(50):
        axis = rng.normal(size=3)
        rv = axis / np.linalg.norm(axis) * angle
        p = pose(*rng.normal(size=3), rotvec_to_matrix(rv))
        v = pose_to_vector(p)
        assert np.linalg.norm(v[3:]) <= math.pi + 1e-15
        assert np.allclose(vector_to_pose(v), p, atol=1e-12)
        if angle < math.pi - 1e-3:
            assert np.allclose(v[3:], rv, atol=1e-12)


def test_bad_poses_are_rejected():
    for bad in (np.eye(3), np.full((4, 4), np.nan), pose(0, 0, 0, -np.eye(3)), pose(0, 0, 0, 2 * np.eye(3))):
        with pytest.raises(DeviceError):
            pose_to_vector(bad)
    with pytest.raises(DeviceError):
        vector_to_pose([0, 0, 0, 0, 0])


def test_rtde_child_answers_each_request_and_never_raises():
    class Fake:
        control = receive = None

    assert answer(Fake(), "not json")["error"] == "ValueError"
    assert answer(Fake(), json.dumps({"id": 3, "op": "format_disk"})) == {
        "id": 3, "error": "ValueError", "message": "unknown operation 'format_disk'"}
    assert answer(Fake(), json.dumps({"id": 4, "op": "read"})) == {
        "id": 4, "error": "RuntimeError", "message": "interfaces are not open"}
    assert answer(Fake(), json.dumps({"id": 5, "op": "stopL", "args": [1, 2, 3]}))["error"] == "TypeError"


@pytest.mark.parametrize("polyscope, answers", [
    ((5, 9), False), ((5, 10), True), ((5, 15), True),  # e-Series: ur_rtde's script lines marked $5.10
    ((3, 14), False), ((3, 15), True), ((3, 16), True),  # CB-series: the same lines, marked |3.15
    ((10, 1), True), ((4, 0), False), (None, False),  # 5 on read as the e-Series; an unknown one not asked
])
def test_the_inverse_kinematics_query_is_asked_where_the_control_script_answers_it(polyscope, answers):
    assert ik_answered(polyscope) is answers


@pytest.mark.parametrize("polyscope, answers", [
    ((3, 5), False), ((3, 6), True), ((3, 15), True), ((5, 0), True), ((5, 15), True), ((1, 8), False),
    (None, True),  # ur_rtde's script lines marked $3.6; a controller that names no version is asked
])
def test_the_tcp_offset_is_asked_where_the_control_script_answers_it(polyscope, answers):
    assert tcp_offset_answered(polyscope) is answers


def test_rtde_link_maps_errors_and_ends_the_process_on_a_timeout(arun):
    """Against the real child process with no arm: a failure in the child is DeviceError and the link goes on; ur_rtde's
    RuntimeError (a dropped link, a protocol error) is LinkLost and ends the link; so does a call that outlives its
    timeout (here: the child is stopped with SIGSTOP). Every later call fails at once naming why."""
    async def run():
        link = RTDELink("test link")
        with pytest.raises(LinkLost, match="not connected"):
            await link.call("a read", 10, "read")
        await link.start()
        first = link.pid
        with pytest.raises(DeviceError, match="unknown operation") as bad:
            await link.call("a bad op", 10, "no_such_op")
        assert not isinstance(bad.value, LinkLost) and link.alive
        for sig in (signal.SIGINT, signal.SIGTERM):  # the daemon still needs the client to stop the arm on its way out
            os.kill(first, sig)
        await asyncio.sleep(0.2)
        with pytest.raises(LinkLost, match="test link: a read failed: interfaces are not open"):
            await link.call("a read", 10, "read")
        with pytest.raises(LinkLost, match="a read failed: interfaces are not open; a stop not sent, reconnect first"):
            await link.call("a stop", 10, "stopL", 10.0)
        await link.stop(5)

        link = RTDELink("test link")
        await link.start()
        second = link.pid
        os.kill(second, signal.SIGSTOP)
        with pytest.raises(LinkLost, match="no answer within 0.2 s waiting for a read; the ur_rtde process was stopped"):
            await link.call("a read", 0.2, "read")
        with pytest.raises(LinkLost, match="no answer within 0.2 s.*; a stop not sent, reconnect first"):
            await link.call("a stop", 10, "stopL", 10.0)
        link.post("a posted stop", 10, "stopL", 10.0)  # dropped: the link has ended
        await link.stop(5)
        await link.stop(5)
        return first, second

    assert not any(_alive(pid) for pid in arun(run()))


def test_rtde_link_ends_when_a_call_its_caller_gave_up_on_is_overdue(arun):
    """A caller cancelled while the child is stuck (as when the runner's own timeout is shorter than the arm's): the
    next call does not queue behind the stuck request once that is past its timeout, and stop() does not wait."""
    async def run():
        link = RTDELink("test link")
        await link.start()
        os.kill(link.pid, signal.SIGSTOP)
        stuck = asyncio.ensure_future(link.call("stopL", 0.3, "stopL", 10.0))
        await asyncio.sleep(0.05)
        stuck.cancel()
        with pytest.raises(asyncio.CancelledError):
            await stuck
        assert link.alive  # not overdue yet
        await asyncio.sleep(0.4)
        with pytest.raises(LinkLost, match="stopL got no answer in time; the ur_rtde process was stopped; a read not"):
            await link.call("a read", 30, "read")
        t0 = time.monotonic()
        await link.stop(30)
        return time.monotonic() - t0

    assert arun(run()) < 15  # it did not wait out the 30 s it was given


async def _two_calls_on_a_stopped_child(first: tuple[str, float], second: tuple[str, float]):
    """A link whose child is held still (SIGSTOP), and two calls (what, timeout_s) sent to it in that order; the
    child answers each with an error (an unknown operation) once it goes on."""
    link = RTDELink("test link")
    await link.start()
    os.kill(link.pid, signal.SIGSTOP)
    calls = []
    for what, timeout_s in (first, second):
        calls.append(asyncio.ensure_future(link.call(what, timeout_s, "no_such_op")))
        await asyncio.sleep(0.05)  # sent in this order
    return link, *calls


def test_requests_queued_behind_a_long_call_count_their_timeout_from_their_turn(arun):
    """A long call within its own timeout (the controller's check of a big plan's poses) holds up the watchdog kicks
    posted meanwhile and a call sent after it: neither is late, and the link lives on once the long call is answered.
    The child is held still with SIGSTOP for longer than the queued requests' timeouts, shorter than the long one's."""
    async def run():
        link, long_call, behind = await _two_calls_on_a_stopped_child(("a long check", 5.0), ("a read behind it", 0.3))
        for _ in range(4):  # the kicks keep coming while the check runs
            link.post("kickWatchdog", 0.3, "no_such_op")
            await asyncio.sleep(0.3)
        assert link.alive, "a kick waiting for its turn is not late"
        os.kill(link.pid, signal.SIGCONT)
        results = await asyncio.gather(long_call, behind, return_exceptions=True)
        alive = link.alive
        await link.stop(5)
        return results, alive

    results, alive = arun(run())
    assert alive
    assert all(isinstance(r, DeviceError) and not isinstance(r, LinkLost) for r in results), results  # answered


def test_a_call_queued_behind_a_stuck_one_names_the_stuck_one(arun):
    async def run():
        link, stuck, behind = await _two_calls_on_a_stopped_child(("a stuck move", 0.3), ("a read behind it", 30))
        t0 = time.monotonic()
        results = await asyncio.gather(stuck, behind, return_exceptions=True)
        waited = time.monotonic() - t0
        await link.stop(5)
        return results, waited

    (stuck, behind), waited = arun(run())
    assert isinstance(stuck, LinkLost) and "no answer within 0.3 s waiting for a stuck move" in str(stuck)
    assert isinstance(behind, LinkLost) and "a stuck move" in str(behind)
    assert waited < 15  # not the 30 s of the call behind it


def test_a_cancelled_stop_still_ends_the_process(arun):
    async def run():
        link = RTDELink("test link")
        await link.start()
        pid = link.pid
        os.kill(pid, signal.SIGSTOP)  # it cannot exit by itself
        closing = asyncio.ensure_future(link.stop(30))
        await asyncio.sleep(0.3)
        closing.cancel()
        with pytest.raises(asyncio.CancelledError):
            await closing
        await link.stop(5)  # reaps it and its readers
        return pid

    assert not _alive(arun(run()))


def test_rtde_link_tells_every_waiting_call_that_the_process_died(arun):
    async def run():
        link = RTDELink("test link")
        await link.start()
        os.kill(link.pid, signal.SIGSTOP)  # requests now wait
        waiting = [asyncio.ensure_future(link.call(f"read {i}", 30, "read")) for i in range(3)]
        await asyncio.sleep(0.1)
        os.kill(link.pid, signal.SIGKILL)
        results = await asyncio.gather(*waiting, return_exceptions=True)
        with pytest.raises(LinkLost, match="ur_rtde process ended"):
            await link.call("a later read", 30, "read")
        await link.stop(5)
        return results

    results = arun(run())
    assert all(isinstance(r, LinkLost) for r in results)
    assert all("link closed: the ur_rtde process ended (killed by SIGKILL)" in str(r) for r in results)
    assert [str(r).rsplit("; ", 1)[1] for r in results] == [f"read {i} got no answer" for i in range(3)]


def test_rtde_child_exits_when_its_parent_is_gone_even_with_stdin_held_open(tmp_path):
    """A parent killed while another process still holds the child's stdin open (or while a call blocks): the child
    must not live on with its links to the controller."""
    script = tmp_path / "parent.py"
    script.write_text(
        "import os, subprocess, sys\n"
        "r, w = os.pipe()\n"
        "child = subprocess.Popen([sys.executable, '-m', 'spadscan.daemon.arm.rtde_child', '--parent',\n"
        "                          str(os.getpid())], stdin=r,\n"
        "                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)\n"
        "holder = subprocess.Popen(['sleep', '60'], pass_fds=[w], stdout=subprocess.DEVNULL,\n"
        "                          stderr=subprocess.DEVNULL)\n"
        "print(child.pid, holder.pid, flush=True)\n"
        "os._exit(0)\n")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    child, holder = (int(x) for x in out.stdout.split())
    try:
        deadline = time.monotonic() + 120  # it polls for its parent every second, once it has started
        while _alive(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(child)
    finally:
        os.kill(holder, signal.SIGKILL)
        with contextlib.suppress(ProcessLookupError):
            os.kill(child, signal.SIGKILL)


class FirstMoveLost(URArm):
    """ur_rtde answers the first moveL False without sending it, as when its control stream still holds a stop
    that the receive stream has shown cleared."""

    dropped = False

    async def _call(self, what, op, *args, timeout_s=None):
        if op == "moveL" and not self.dropped:
            self.dropped = True
            return False
        return await super()._call(what, op, *args, timeout_s=timeout_s)


def test_a_move_refused_after_a_stop_that_held_a_move_is_sent_again(ur, arun):
    """A safeguard stop halts an asynchronous move and leaves its running bit set (the program runs on: unlike a
    protective stop, it is not paused and uploaded again). Once the stop is cleared, a refused moveL must not be
    taken for a move the controller took because that stale bit still says 'running': the move is sent again and
    arrives (instead of waiting out its motion budget for a move that never started)."""
    async def run():
        arm = FirstMoveLost(ur.host, frequency=100.0, stale_after_s=1.0, timeout_s=5.0, watchdog_hz=1.0)
        try:
            await arm.connect()
            arm.dropped = True  # the first move goes through
            long_move = asyncio.create_task(arm.move_to(pose(0.4, 0.0, 0.3, DOWN), speed=0.05, accel=ACCEL))
            await wait_for_moves(ur, 1)
            while not (await arm._read("test", progress=True)).moving:
                await asyncio.sleep(0.01)
            ur.safeguard_stop()
            with pytest.raises(ArmFault, match="safeguard stop"):
                await asyncio.wait_for(long_move, 30)
            ur.clear_safeguard_stop()
            await cleared(arm)
            await arm.clear_fault()
            held = (await arm._read("test", progress=True)).moving
            arm.dropped = False  # the next moveL is answered False and not sent
            await asyncio.wait_for(arm.move_to(pose(0.35, 0.05, 0.3, DOWN)), 60)
            return held, (await arm.state()).tcp_pose
        finally:
            await arm.close()

    held, reached = arun(run())
    assert held, "the halted move's running bit was expected to stay set (the scenario needs it)"
    assert np.allclose(reached[:3, 3], [0.35, 0.05, 0.3], atol=2e-3)
    assert [tuple(np.round(m.target[:2], 3)) for m in ur.moves][-1] == (0.35, 0.05)
