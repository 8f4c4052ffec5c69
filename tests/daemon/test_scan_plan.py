"""Scan plans: schedules, visiting order, hand-eye, workspace checks."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from spadscan.daemon.arm.pose_convert import matrix_to_rotvec, rotvec_to_matrix
from spadscan.daemon.config import ArmConfig, ScanConfig
from spadscan.daemon.scan_plan import (build_plan, invert_rigid, order_nearest, order_serpentine, path_length,
                                       sensor_from_tcp, tcp_from_sensor)
from spadscan.daemon.workspace import _move_samples, check_workspace
from spadscan.protocol.errors import ConfigError

HAND_EYE = np.array([[0.0, -1, 0, 0.01], [1, 0, 0, -0.02], [0, 0, 1, 0.05], [0, 0, 0, 1]])


def arm(**kw) -> ArmConfig:
    return replace(ArmConfig(), **{"hand_eye": HAND_EYE, **kw})


def scan(**kw) -> ScanConfig:
    return replace(ScanConfig(), **kw)


DOWN = np.diag([1.0, -1.0, -1.0])  # tool z pointing down


def pose_at(xyz, rot=np.eye(3)) -> np.ndarray:
    p = np.eye(4)
    p[:3, :3], p[:3, 3] = rot, xyz
    return p


def test_invert_rigid():
    m = HAND_EYE.copy()
    np.testing.assert_allclose(invert_rigid(m) @ m, np.eye(4), atol=1e-12)
    stack = np.stack([m, np.eye(4)])
    np.testing.assert_allclose(invert_rigid(stack) @ stack, np.stack([np.eye(4)] * 2), atol=1e-12)


@pytest.mark.parametrize("schedule, views", [("fibonacci", 40), ("rings", 36)])
def test_plan_puts_the_sensor_on_the_sphere_looking_at_the_target(schedule, views):
    target = np.array([0.45, 0.0, 0.05])
    plan = build_plan(scan(views=views, schedule=schedule, rings=4, radius_m=0.3, target=target,
                           min_elevation_deg=15, max_elevation_deg=75), arm())
    assert len(plan) == views and plan.tcp_poses.shape == (views, 4, 4)
    pos = plan.sensor_poses[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(pos - target, axis=1), 0.3, atol=1e-12)
    view = (target - pos) / 0.3
    np.testing.assert_allclose(np.einsum("ni,ni->n", plan.sensor_poses[:, :3, 2], view), 1.0, atol=1e-9)
    elev = np.degrees(np.arcsin((pos[:, 2] - target[2]) / 0.3))
    assert elev.min() >= 15 - 1e-9 and elev.max() <= 75 + 1e-9
    # Hand-eye: the TCP carries the sensor exactly to its pose.
    np.testing.assert_allclose(sensor_from_tcp(plan.tcp_poses, HAND_EYE), plan.sensor_poses, atol=1e-12)
    np.testing.assert_allclose(tcp_from_sensor(plan.sensor_poses, HAND_EYE), plan.tcp_poses, atol=1e-12)


def test_nearest_order_is_a_permutation_and_shortens_travel():
    planned = build_plan(scan(views=100, order="planned"), arm())
    nearest = build_plan(scan(views=100, order="nearest"), arm())
    perm = nearest.description["generated_order"]
    assert sorted(perm) == list(range(100))
    np.testing.assert_allclose(nearest.sensor_poses, planned.sensor_poses[perm])
    short, long_ = path_length(nearest.tcp_poses[:, :3, 3]), path_length(planned.tcp_poses[:, :3, 3])
    assert short < 0.5 * long_, (short, long_)  # the golden-angle order jumps across the hemisphere every step


def test_nearest_order_starts_where_the_arm_is():
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    assert order_nearest(pts, start=np.array([3.1, 0, 0])).tolist() == [3, 2, 1, 0]
    assert order_nearest(pts).tolist() == [0, 1, 2, 3]
    assert order_nearest(np.zeros((0, 3))).tolist() == []


def test_serpentine_alternates_direction_per_ring():
    s = scan(views=24, schedule="rings", rings=3, order="serpentine")
    plan = build_plan(s, arm())
    pos = plan.sensor_poses[:, :3, 3] - s.target
    elev = np.arcsin(pos[:, 2] / np.linalg.norm(pos, axis=1))
    rings = [elev[i * 8:(i + 1) * 8] for i in range(3)]
    assert all(np.ptp(r) < 1e-9 for r in rings)  # each block of 8 is one ring
    assert rings[0][0] > rings[1][0] > rings[2][0]  # from the top down
    azim = np.unwrap(np.arctan2(pos[:, 1], pos[:, 0]))
    d0, d1 = np.diff(azim[:8]), np.diff(azim[8:16])
    assert np.all(d0 > 0) and np.all(d1 < 0)
    planned = build_plan(replace(s, order="planned"), arm())
    assert path_length(plan.tcp_poses[:, :3, 3]) < path_length(planned.tcp_poses[:, :3, 3])


def test_serpentine_on_fibonacci_is_a_shorter_permutation():
    pts = build_plan(scan(views=64, order="planned"), arm()).sensor_poses[:, :3, 3]
    perm = order_serpentine(pts, np.zeros(3), bands=6)
    assert sorted(perm.tolist()) == list(range(64))
    assert path_length(pts[perm]) < 0.5 * path_length(pts)


def test_jitter_is_seeded_and_bounded():
    base = build_plan(scan(views=30, order="planned"), arm()).sensor_poses
    a = build_plan(scan(views=30, order="planned", jitter_deg=5, seed=7), arm()).sensor_poses
    b = build_plan(scan(views=30, order="planned", jitter_deg=5, seed=7), arm()).sensor_poses
    c = build_plan(scan(views=30, order="planned", jitter_deg=5, seed=8), arm()).sensor_poses
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    np.testing.assert_allclose(a[:, :3, 3], base[:, :3, 3])  # the sensor stays put, only turns
    cos = np.clip(np.einsum("ni,ni->n", a[:, :3, 2], base[:, :3, 2]), -1, 1)
    tilt = np.degrees(np.arccos(cos))
    assert tilt.max() <= 5 + 1e-6 and tilt.max() > 0.5


def test_workspace_box_names_the_first_bad_pose():
    s = scan(views=50, order="planned", radius_m=0.4, min_elevation_deg=5, max_elevation_deg=85)
    plan = build_plan(s, arm())
    z = np.minimum(plan.tcp_poses[:, 2, 3], plan.sensor_poses[:, 2, 3])  # the flange or the sensor, lower one
    limit = float(np.sort(z)[10])  # some poses fall below this floor
    first_bad = int(np.flatnonzero(z < limit)[0])
    a = arm(workspace_min=np.array([-1, -1, limit]), workspace_max=np.array([1.0, 1, 1]))
    with pytest.raises(ConfigError) as info:
        build_plan(s, a, where="scan 'x'")
    msg = str(info.value)
    assert f"pose {first_bad} of 50" in msg and "below workspace_min" in msg and "z = " in msg
    assert "\n" not in msg and msg.startswith("scan 'x'")


def test_the_sensor_and_its_bracket_must_stay_in_the_workspace_not_only_the_flange():
    """The flange at z = 0.12 looking down puts a sensor 5 cm out at z = 0.07, below a 0.08 m floor."""
    box = dict(workspace_min=np.array([-1, -1, 0.08]), workspace_max=np.array([1.0, 1, 1]))
    he = np.eye(4)
    he[2, 3] = 0.05
    tcp = pose_at([0.4, 0.0, 0.12], DOWN)[None]
    check_workspace(tcp, arm(hand_eye=np.eye(4), **box), "plan")  # a sensor at the flange would be fine
    with pytest.raises(ConfigError, match=r"pose 0 of 1: .* the sensor \(TCP x hand_eye\) is outside the workspace: "
                                          r"z = 0.070 m is below workspace_min 0.080 m"):
        check_workspace(tcp, arm(hand_eye=he, **box), "plan")
    tcp = pose_at([0.4, 0.0, 0.15], DOWN)[None]  # sensor at 0.10 m: clear of the floor, its bracket is not
    check_workspace(tcp, arm(hand_eye=he, **box), "plan")
    with pytest.raises(ConfigError, match="below workspace_min 0.080 m plus bracket_radius_m 0.03 = 0.110 m"):
        check_workspace(tcp, arm(hand_eye=he, bracket_radius_m=0.03, **box), "plan")


def test_the_base_keeps_a_cylinder_clear_not_only_a_sphere():
    """High above the base a pose is far from its origin, yet in the arm's own column."""
    high = pose_at([0.05, 0.0, 0.7], DOWN)[None]
    check_workspace(high, arm(hand_eye=np.eye(4), min_reach_m=0.2), "plan")
    with pytest.raises(ConfigError, match=r"0.050 m from the base's vertical axis, inside keepout_radius_m 0.15"):
        check_workspace(high, arm(hand_eye=np.eye(4), min_reach_m=0.2, keepout_radius_m=0.15), "plan")
    across = np.stack([pose_at([0.3, 0.05, 0.6], DOWN), pose_at([-0.3, 0.05, 0.6], DOWN)])
    check_workspace(across, arm(hand_eye=np.eye(4), min_reach_m=0.2), "plan")
    with pytest.raises(ConfigError, match=r"straight move to pose 1 of 2 brings the TCP 0.050 m from the base's "
                                          r"vertical axis"):
        check_workspace(across, arm(hand_eye=np.eye(4), keepout_radius_m=0.15), "plan")


def test_a_straight_move_may_not_swing_the_sensor_into_the_base():
    """Both ends clear, the flange's straight line clear; the tool turning on the way swings a sensor 20 cm out
    through the base's keep-out cylinder."""
    he = np.eye(4)
    he[2, 3] = 0.2
    a = pose_at([0.3, -0.25, 0.35], np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]))  # sensor along -y
    b = pose_at([0.3, 0.25, 0.35], np.array([[0.0, 0, -1], [-1, 0, 0], [0, 1, 0]]))  # sensor along -x
    lim = arm(hand_eye=he, keepout_radius_m=0.25)
    check_workspace(a[None], lim, "plan")
    check_workspace(b[None], lim, "plan")
    with pytest.raises(ConfigError, match=r"straight move to pose 1 of 2 brings the sensor 0.12[12] m from the base's "
                                          r"vertical axis, inside keepout_radius_m 0.25"):
        check_workspace(np.stack([a, b]), lim, "plan")


def test_reach_limits():
    s = scan(views=20, order="planned", target=np.array([0.5, 0.0, 0.0]), radius_m=0.3)
    reach = np.linalg.norm(build_plan(s, arm()).tcp_poses[:, :3, 3], axis=1)
    with pytest.raises(ConfigError, match="exceeds max_reach_m"):
        build_plan(s, arm(max_reach_m=float(reach.max()) - 0.01))
    with pytest.raises(ConfigError, match="below min_reach_m"):
        build_plan(s, arm(min_reach_m=float(reach.min()) + 0.01))
    build_plan(s, arm(min_reach_m=float(reach.min()) - 0.01, max_reach_m=float(reach.max()) + 0.01))


def test_straight_moves_must_keep_clear_of_the_base():
    a = arm(min_reach_m=0.2)
    tcp = np.stack([np.eye(4)] * 2)
    tcp[0, :3, 3] = [0.5, 0.01, 0.1]
    tcp[1, :3, 3] = [-0.5, 0.01, 0.1]  # both ends 0.5 m out, the line passes 0.1 m from the base
    with pytest.raises(ConfigError, match="straight move to pose 1 of 2 passes 0.100 m"):
        check_workspace(tcp, a, "plan")
    check_workspace(tcp[:1], a, "plan")
    with pytest.raises(ConfigError, match="straight move to pose 0 of 1"):
        check_workspace(tcp[:1], a, "plan", start=pose_at([-0.5, 0.0, 0.1]))


def test_non_finite_pose_is_refused():
    tcp = np.stack([np.eye(4)])
    tcp[0, 0, 3] = math.inf
    with pytest.raises(ConfigError, match="pose 0 of 1: TCP position is not finite"):
        check_workspace(tcp, arm(), "plan")


def test_the_sensor_samples_along_a_move_follow_the_turning_tool():
    """The sensor's path along a straight move is the flange's plus the hand-eye offset turned by the share of the
    move's rotation reached so far: checked against one rotation matrix per sample."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        a, b = np.eye(4), np.eye(4)
        a[:3, :3], b[:3, :3] = (rotvec_to_matrix(rng.normal(size=3)) for _ in range(2))
        a[:3, 3], b[:3, 3] = rng.uniform(-0.4, 0.4, (2, 3))
        flange, sensor = _move_samples(a, b, HAND_EYE)
        turn = matrix_to_rotvec(a[:3, :3].T @ b[:3, :3])
        s = np.linspace(0.0, 1.0, len(flange))
        expected = [f + a[:3, :3] @ rotvec_to_matrix(t * turn) @ HAND_EYE[:3, 3] for f, t in zip(flange, s)]
        np.testing.assert_allclose(sensor, expected, atol=1e-12)
        np.testing.assert_allclose(sensor[-1], (b @ HAND_EYE)[:3, 3], atol=1e-12)


def test_a_start_already_outside_the_workspace_is_named_as_such_not_as_the_move():
    """An arm at rest above the box was refused for "the straight move to pose 0": the move was not the problem."""
    box = dict(workspace_min=np.array([-1, -1, 0.0]), workspace_max=np.array([1.0, 1, 0.6]))
    start = pose_at([0.4, 0.0, 0.7], DOWN)
    with pytest.raises(ConfigError, match=r"the arm stands where it may not: z = 0.700 m is above workspace_max "
                                          r"0.600 m \(\[arm\] limits\); jog it into the workspace"):
        check_workspace(pose_at([0.4, 0.0, 0.3], DOWN)[None], arm(hand_eye=np.eye(4), **box), "plan", start=start)


def test_a_ring_schedule_up_to_the_zenith_is_refused_before_the_arm_moves():
    """Its top ring's views would all stand at one point: the arm would visit it `views / rings` times."""
    with pytest.raises(ConfigError) as info:
        build_plan(scan(schedule="rings", rings=4, views=32, min_elevation_deg=20, max_elevation_deg=90), arm())
    assert "8 views at one viewpoint" in str(info.value) and "\n" not in str(info.value)
    # A scan config that skipped config.check_scan (which refuses it naming the key) is still refused saying where.
    with pytest.raises(ConfigError, match=r"^rig\.toml: \[scan\] defaults: schedule 'rings': a ring at \+90 deg"):
        build_plan(scan(schedule="rings", rings=4, views=32, max_elevation_deg=90), arm(),
                   where="rig.toml: [scan] defaults")
    assert len(build_plan(scan(schedule="rings", rings=4, views=32, min_elevation_deg=20, max_elevation_deg=80),
                          arm()).sensor_poses) == 32
