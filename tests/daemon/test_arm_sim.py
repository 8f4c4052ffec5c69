"""The simulated arm: motion timing, actual vs commanded pose, fake joints, injected faults."""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np
import pytest

from spadscan.daemon.arm import sim as sim_module
from spadscan.daemon.arm.pose_convert import matrix_to_rotvec, rotvec_to_matrix
from spadscan.daemon.arm.sim import HOME, SimArm, SimArmFaults, fake_joints, interpolate_pose, trapezoid_time
from spadscan.daemon.arm.stops import EMERGENCY_STOP, PROTECTIVE_STOP, SAFEGUARD_STOP, stop_name
from spadscan.daemon.devices import ArmFault, LinkLost
from spadscan.protocol.errors import ConfigError


def pose_at(x, y, z, rotvec=(math.pi, 0.0, 0.0)) -> np.ndarray:
    p = np.eye(4)
    p[:3, :3] = rotvec_to_matrix(np.array(rotvec))
    p[:3, 3] = (x, y, z)
    return p


@pytest.mark.parametrize("v", [[0, 0, 0], [0.3, -0.2, 0.1], [math.pi - 1e-9, 0, 0], [0, 2.0, -1.0],
                               [1.5, 1.5, 1.5]])
def test_rotvec_round_trip(v):
    r = rotvec_to_matrix(np.array(v, float))
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rotvec_to_matrix(matrix_to_rotvec(r)), r, atol=1e-7)


def test_trapezoid_time():
    assert trapezoid_time(0.0, 0.25, 1.0) == 0.0
    # Long move: cruise. d / v + v / a.
    assert trapezoid_time(1.0, 0.25, 1.0) == pytest.approx(4.25)
    # Short move: triangle profile, never reaches the speed.
    assert trapezoid_time(0.01, 0.25, 1.0) == pytest.approx(2 * math.sqrt(0.01))


def test_motion_time_from_distance_speed_and_scale(arun):
    arm = SimArm(speed=0.5, time_scale=0.1)
    a, b = pose_at(0.3, 0, 0.4), pose_at(0.3, 0.2, 0.4)
    # The move's speed is capped at the arm's speed (0.5 m/s); then scaled by 0.1.
    assert arm.motion_time(a, b, speed=2.0, accel=10.0) == pytest.approx(0.1 * trapezoid_time(0.2, 0.5, 10.0))
    assert arm.motion_time(a, b, speed=0.1, accel=10.0) == pytest.approx(0.1 * trapezoid_time(0.2, 0.1, 10.0))
    assert SimArm(motion_time_s=0.3, time_scale=0.5).motion_time(a, b, 0.1, 1.0) == pytest.approx(0.15)
    assert SimArm(motion_time_s=0).motion_time(a, b, 0.1, 1.0) == 0.0


def test_move_takes_its_time_and_arrives_exactly(arun):
    async def scenario():
        arm = SimArm(motion_time_s=1.0)
        await arm.connect()
        goal = pose_at(0.4, 0.1, 0.3)
        t0 = time.monotonic()
        task = asyncio.create_task(arm.move_to(goal, 0.1, 0.5))
        while np.array_equal(arm.actual_pose(), HOME):  # the move has begun (a second's margin before it ends)
            await asyncio.sleep(0.01)
        mid = arm.actual_pose()
        await task
        elapsed = time.monotonic() - t0
        state = await arm.state()
        await arm.release()
        await arm.close()
        return mid, elapsed, state, goal

    mid, elapsed, state, goal = arun(scenario())
    assert elapsed >= 1.0
    # Mid-move the actual pose lies strictly between home and goal, on the straight line.
    s = (mid[0, 3] - HOME[0, 3]) / (goal[0, 3] - HOME[0, 3])
    assert 0 < s < 1
    np.testing.assert_allclose(mid[:3, 3], (1 - s) * HOME[:3, 3] + s * goal[:3, 3], atol=1e-9)
    np.testing.assert_allclose(state.tcp_pose, goal, atol=1e-12)
    np.testing.assert_allclose(state.joints, fake_joints(goal))
    assert not state.protective_stop


def test_pose_noise_moves_the_actual_pose_a_little(arun):
    async def scenario():
        arm = SimArm(motion_time_s=0, pose_noise_m=0.001, seed=3)
        goal = pose_at(0.4, 0.1, 0.3)
        await arm.move_to(goal, 0.1, 0.5)
        return (await arm.state()).tcp_pose, goal

    actual, goal = arun(scenario())
    err = np.linalg.norm(actual[:3, 3] - goal[:3, 3])
    assert 0 < err < 0.01
    np.testing.assert_allclose(actual[:3, :3], goal[:3, :3])


class LateClock:
    """The sim arm's clock on a loaded machine: every reading is `lag_s` later than the one before."""

    def __init__(self, lag_s: float):
        self.lag_s, self.offset = lag_s, 0.0

    def monotonic(self) -> float:
        self.offset += self.lag_s
        return time.monotonic() + self.offset


@pytest.mark.parametrize("lag_s", [0.0, 10.0])
def test_protective_stop_on_kth_move_freezes_exactly_half_way(arun, monkeypatch, lag_s):
    monkeypatch.setattr(sim_module, "time", LateClock(lag_s))

    async def scenario():
        arm = SimArm(motion_time_s=0.02, faults=SimArmFaults(protective_stop_on_moves=(2,)))
        first, second = pose_at(0.4, 0, 0.3), pose_at(0.4, 0.2, 0.3, rotvec=(0.0, math.pi / 2, 0.0))
        await arm.move_to(first, 0.1, 0.5)
        with pytest.raises(ArmFault, match="protective stop"):
            await arm.move_to(second, 0.1, 0.5)
        state = await arm.state()
        with pytest.raises(ArmFault, match="protective stop"):  # refused until the operator clears it
            await arm.move_to(second, 0.1, 0.5)
        arm.clear_protective_stop()
        await arm.move_to(second, 0.1, 0.5)
        return state, (await arm.state()).tcp_pose, first, second

    state, final, first, second = arun(scenario())
    assert state.protective_stop
    np.testing.assert_array_equal(state.tcp_pose, interpolate_pose(first, second, 0.5))
    np.testing.assert_allclose(final, second, atol=1e-12)


def test_clear_fault_clears_the_protective_stop_and_reconnect_needs_the_link(arun):
    async def scenario():
        arm = SimArm(motion_time_s=0, faults=SimArmFaults(protective_stop_on_moves=(1,)))
        with pytest.raises(ArmFault, match="protective stop"):
            await arm.move_to(pose_at(0.4, 0, 0.3), 0.1, 0.5)
        await arm.clear_fault()  # what the runner calls on `ctl resume` after an arm fault
        await arm.move_to(pose_at(0.4, 0, 0.3), 0.1, 0.5)
        arm.drop_link()
        with pytest.raises(LinkLost):
            await arm.reconnect()
        arm.restore_link()
        await arm.reconnect()
        return arm.moves, arm.connected

    assert arun(scenario()) == (2, True)


@pytest.mark.parametrize("kwargs", [{"motion_time_s": -1.0}, {"motion_time_s": math.nan}, {"speed": 0.0},
                                    {"speed": math.inf}, {"time_scale": -0.1}, {"pose_noise_m": math.nan},
                                    {"speed": True}, {"home": np.eye(3)}])
def test_bad_arguments_are_config_errors(kwargs):
    with pytest.raises(ConfigError, match="sim arm"):
        SimArm(**kwargs)


def test_protective_stop_on_demand_and_stop(arun):
    async def scenario():
        arm = SimArm(motion_time_s=30.0)  # stopped long before it could arrive, however loaded the machine
        task = asyncio.create_task(arm.move_to(pose_at(0.4, 0.2, 0.3), 0.1, 0.5))
        await asyncio.sleep(0.05)
        await arm.stop()
        # The stopped move returns at once, as a real moveL does, not after the 30 s the move would have taken.
        with pytest.raises(ArmFault, match="stopped before it arrived"):
            await asyncio.wait_for(task, 10.0)
        stopped = arm.actual_pose()
        await asyncio.sleep(0.05)
        still = arm.actual_pose()
        task = asyncio.create_task(arm.move_to(pose_at(0.4, -0.2, 0.3), 0.1, 0.5))
        await asyncio.sleep(0.05)
        arm.trigger_protective_stop()
        with pytest.raises(ArmFault, match="protective stop"):
            await asyncio.wait_for(task, 10.0)
        return stopped, still

    stopped, still = arun(scenario())
    np.testing.assert_allclose(stopped, still)  # a stopped arm does not drift on


def test_link_drop_and_restore(arun):
    """A dropped link stays lost after it is restored until the arm reconnects, as a real arm's closed connection
    does (the runner reconnects on resume)."""
    async def scenario():
        arm = SimArm(motion_time_s=0.02, faults=SimArmFaults(link_drop_on_moves=(1,)))
        with pytest.raises(LinkLost):
            await arm.move_to(pose_at(0.4, 0, 0.3), 0.1, 0.5)
        with pytest.raises(LinkLost):
            await arm.state()
        arm.restore_link()
        with pytest.raises(LinkLost, match="reconnect first"):
            await arm.state()
        await arm.reconnect()
        await arm.move_to(pose_at(0.4, 0, 0.3), 0.1, 0.5)
        arm.drop_link()
        with pytest.raises(LinkLost):
            await arm.move_to(pose_at(0.4, 0.1, 0.3), 0.1, 0.5)
        return arm.moves

    assert arun(scenario()) == 2


def test_bad_targets_are_refused(arun):
    async def scenario():
        arm = SimArm(motion_time_s=0)
        bad = pose_at(0.4, 0, 0.3)
        bad[0, 3] = np.nan
        with pytest.raises(ArmFault, match="finite"):
            await arm.move_to(bad, 0.1, 0.5)
        with pytest.raises(ArmFault, match="positive"):
            await arm.move_to(pose_at(0.4, 0, 0.3), 0.0, 0.5)
        return arm.moves

    assert arun(scenario()) == 0


def test_fake_joints_follow_the_pose():
    a, b = pose_at(0.4, 0.1, 0.3), pose_at(0.4, 0.1, 0.31)
    ja, jb = fake_joints(a), fake_joints(b)
    assert ja.shape == (6,) and np.all(np.isfinite(ja))
    assert 0 < np.abs(ja - jb).max() < 0.1
    np.testing.assert_array_equal(fake_joints(a), ja)


def test_interpolate_pose_ends_and_rigidity():
    a, b = pose_at(0, 0, 0.5), pose_at(0.2, 0.1, 0.3, rotvec=(0.2, 2.5, 0.1))
    np.testing.assert_allclose(interpolate_pose(a, b, 0.0), a, atol=1e-12)
    np.testing.assert_allclose(interpolate_pose(a, b, 1.0), b, atol=1e-9)
    m = interpolate_pose(a, b, 0.37)
    np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12)


STOPS = {PROTECTIVE_STOP: "protective_stop_on_moves", SAFEGUARD_STOP: "safeguard_stop_on_moves",
         EMERGENCY_STOP: "emergency_stop_on_moves"}


@pytest.mark.parametrize("kind", list(STOPS))
def test_each_safety_stop_is_named_in_the_move_the_refusal_and_the_state(arun, kind):
    """A stop half way through a chosen move, and one at rest: the move, the moves refused after it and the state
    name the stop (the operator clears each in its own way); clear_fault (the runner's step on resume) clears it."""
    async def scenario():
        arm = SimArm(motion_time_s=0.02, faults=SimArmFaults(**{STOPS[kind]: (1,)}))
        with pytest.raises(ArmFault, match=f"^arm \\(sim\\): {kind} during move 1; .*, then resume$"):
            await arm.move_to(pose_at(0.4, 0, 0.3), 0.1, 0.5)
        held = await arm.state()
        with pytest.raises(ArmFault, match=f"{kind}; .*, then resume"):
            await arm.move_to(pose_at(0.4, 0, 0.3), 0.1, 0.5)
        await arm.clear_fault()
        await arm.move_to(pose_at(0.4, 0, 0.3), 0.1, 0.5)
        free = await arm.state()
        arm.trigger_stop(kind)  # at rest, as while the sensor captures a pose
        at_rest = await arm.state()
        return held, free, at_rest

    held, free, at_rest = arun(scenario())
    assert (held.safety_stop, held.protective_stop, stop_name(held)) == (kind, True, kind)
    assert (free.safety_stop, free.protective_stop, stop_name(free)) == (None, False, None)
    assert (at_rest.safety_stop, stop_name(at_rest)) == (kind, kind)


def test_an_unknown_stop_is_refused():
    with pytest.raises(ValueError, match="unknown safety stop"):
        SimArm().trigger_stop("coffee break")
