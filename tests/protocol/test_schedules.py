"""Pose schedules: counts, radius, elevations, view direction, rigid rotations."""

import numpy as np
import pytest

from spadscan.protocol import schedules
from spadscan.protocol.errors import SimulationError


def assert_rigid(poses):
    rot = poses[:, :3, :3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    np.testing.assert_array_equal(poses[:, 3], np.broadcast_to([0, 0, 0, 1], (len(poses), 4)))


def elevations_deg(poses, target):
    rel = poses[:, :3, 3] - target
    return np.degrees(np.arcsin(rel[:, 2] / np.linalg.norm(rel, axis=1)))


def assert_looks_at(poses, target):
    rel = np.asarray(target) - poses[:, :3, 3]
    rel /= np.linalg.norm(rel, axis=1, keepdims=True)
    np.testing.assert_allclose(poses[:, :3, 2], rel, atol=1e-12)


@pytest.mark.parametrize("up", [(0, 0, 1), (0, 0, -1), (1, 0, 0)])
def test_look_at_is_rigid_even_straight_down(up):
    target = np.array([0.1, -0.2, 0.0])
    for eye in ([0.1, -0.2, 0.5], [0.4, 0.1, 0.2], [0.1, -0.2, -0.3], [0.1 + 1e-9, -0.2, 0.5]):
        pose = schedules.look_at(eye, target, up)
        assert_rigid(pose[None])
        assert_looks_at(pose[None], target)
        np.testing.assert_array_equal(pose[:3, 3], eye)


def test_look_at_keeps_up_in_the_view():
    pose = schedules.look_at([1.0, 0, 0], [0, 0, 0])
    np.testing.assert_allclose(pose[:3, 1], [0, 0, 1], atol=1e-12)  # sensor +y is world up at the horizon
    with pytest.raises(SimulationError, match="coincide"):
        schedules.look_at([1, 2, 3], [1, 2, 3])


def test_fibonacci_hemisphere_covers_the_band_evenly():
    target = np.array([0.05, 0.0, 0.1])
    poses = schedules.fibonacci_hemisphere(256, 0.5, target, 0.0, 86.0)
    assert poses.shape == (256, 4, 4)
    assert_rigid(poses)
    assert_looks_at(poses, target)
    np.testing.assert_allclose(np.linalg.norm(poses[:, :3, 3] - target, axis=1), 0.5, rtol=1e-12)
    el = elevations_deg(poses, target)
    assert 0.0 < el.min() < 0.5 and 84.0 < el.max() < 86.0
    assert np.all(np.diff(el) < 0)  # from the top down
    # equal area: sin(elevation) steps evenly; azimuths spread (no two consecutive views close together)
    np.testing.assert_allclose(np.diff(np.sin(np.radians(el))), -np.sin(np.radians(86.0)) / 256, rtol=1e-9)
    rel = poses[:, :3, 3] - target
    az = np.arctan2(rel[:, 1], rel[:, 0])
    hist, _ = np.histogram(az, bins=8, range=(-np.pi, np.pi))
    assert hist.min() >= 28


def test_elevation_rings():
    poses = schedules.elevation_rings(3, 8, 0.4, (0, 0, 0.05), 10.0, 70.0)
    assert poses.shape == (24, 4, 4)
    assert_rigid(poses)
    assert_looks_at(poses, [0, 0, 0.05])
    el = elevations_deg(poses, np.array([0, 0, 0.05]))
    np.testing.assert_allclose(sorted(set(np.round(el, 9))), [10.0, 40.0, 70.0])
    np.testing.assert_allclose(np.linalg.norm(poses[:, :3, 3] - [0, 0, 0.05], axis=1), 0.4)


def test_a_ring_of_one_view_may_stand_at_the_zenith():
    poses = schedules.elevation_rings(3, 1, 0.4, (0, 0, 0), 30.0, 90.0)
    assert_rigid(poses)
    np.testing.assert_allclose(poses[-1, :3, 3], [0, 0, 0.4], atol=1e-12)


def test_jitter_turns_about_the_sensor_within_the_limit():
    poses = schedules.fibonacci_hemisphere(100, 0.5)
    rng = np.random.default_rng(7)
    out = schedules.jitter_orientations(poses, 10.0, rng)
    assert_rigid(out)
    np.testing.assert_array_equal(out[:, :3, 3], poses[:, :3, 3])
    angle = np.degrees(np.arccos(np.clip((np.trace(poses[:, :3, :3].transpose(0, 2, 1) @ out[:, :3, :3],
                                                   axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert angle.max() <= 10.0 + 1e-9 and angle.max() > 8.0 and angle.min() >= 0
    again = schedules.jitter_orientations(poses, 10.0, np.random.default_rng(7))
    np.testing.assert_array_equal(out, again)
    np.testing.assert_allclose(schedules.jitter_orientations(poses, 0.0, rng), poses, atol=1e-15)


@pytest.mark.parametrize("call", [
    lambda: schedules.fibonacci_hemisphere(0, 0.5),
    lambda: schedules.fibonacci_hemisphere(10, -1.0),
    lambda: schedules.fibonacci_hemisphere(10, 0.5, min_elevation_deg=50, max_elevation_deg=40),
    lambda: schedules.elevation_rings(0, 4, 0.5),
    lambda: schedules.elevation_rings(4, 8, 0.5, min_elevation_deg=0, max_elevation_deg=90),  # 8 views at one point
    lambda: schedules.elevation_rings(2, 8, 0.5, min_elevation_deg=-90, max_elevation_deg=30),
    lambda: schedules.fibonacci_hemisphere(10, 0.5, target=(0, 0)),
    lambda: schedules.jitter_orientations(np.eye(4)[None], 200.0, np.random.default_rng()),
])
def test_bad_schedules_raise(call):
    with pytest.raises(SimulationError):
        call()


@pytest.mark.parametrize("call, message", [
    (lambda: schedules.fibonacci_hemisphere(16, 0.5, min_elevation_deg=90, max_elevation_deg=90),
     "a spiral band of zero width at +90 deg elevation puts its 16 views at one viewpoint (straight above the "
     "target)"),
    (lambda: schedules.fibonacci_hemisphere(16, 0.5, min_elevation_deg=-90, max_elevation_deg=-90),
     "a spiral band of zero width at -90 deg elevation puts its 16 views at one viewpoint (straight below"),
    (lambda: schedules.elevation_rings(3, 8, 0.5, min_elevation_deg=30, max_elevation_deg=30),
     "3 rings in a band of zero width (30 deg) all stand at one elevation, every other ring on the same poses"),
    (lambda: schedules.elevation_rings(2, 8, 0.5, min_elevation_deg=45, max_elevation_deg=45),
     "2 rings in a band of zero width (45 deg) all stand at one elevation; widen the band"),
], ids=["spiral-top", "spiral-bottom", "three-rings", "two-rings"])
def test_schedules_that_would_repeat_poses_are_one_line_errors(call, message):
    """These gave 16 copies of one pose, or rings 0 and 2 on the same poses, without a word."""
    with pytest.raises(SimulationError) as info:
        call()
    assert str(info.value).startswith(message) and "\n" not in str(info.value)


@pytest.mark.parametrize("poses", [
    schedules.fibonacci_hemisphere(1, 0.5, min_elevation_deg=90, max_elevation_deg=90),  # one view at the top
    schedules.fibonacci_hemisphere(16, 0.5, min_elevation_deg=30, max_elevation_deg=30),  # a circle: golden angles
    schedules.fibonacci_hemisphere(16, 0.5, min_elevation_deg=89.9, max_elevation_deg=90),
    schedules.elevation_rings(1, 8, 0.5, min_elevation_deg=30, max_elevation_deg=30),  # one ring: min = max places it
    schedules.elevation_rings(4, 8, 0.5, min_elevation_deg=10, max_elevation_deg=80),
], ids=["one-at-the-top", "spiral-circle", "spiral-near-the-top", "one-ring", "rings"])
def test_the_schedules_still_allowed_give_every_view_a_pose_of_its_own(poses):
    distinct = np.unique(np.round(poses.reshape(len(poses), -1), 9), axis=0)
    assert len(distinct) == len(poses)


@pytest.mark.parametrize("n_rings, per_ring, elevation", [
    (n, k, e) for n in (1, 2, 3, 4) for k in (1, 2, 7) for e in (-90, -30, 0, 45, 90)])
def test_rings_repeat_note_speaks_exactly_when_a_pose_repeats(n_rings, per_ring, elevation):
    """It follows the poses themselves: two views on one position (and so one pose: each looks at the target) are
    named, and nothing else is (2 rings off the poles are one ring of twice the views). A ring of several views at a
    pole is ring_at_pole_deg's, and refused with it."""
    eyes = raw_ring_eyes(n_rings, per_ring, elevation)
    repeats = len(np.unique(np.round(eyes, 9), axis=0)) < len(eyes)
    note = schedules.rings_repeat_note(n_rings, elevation, elevation)
    at_pole = schedules.ring_at_pole_deg(n_rings, per_ring, elevation, elevation) is not None
    assert (note is not None or at_pole) == repeats


def raw_ring_eyes(n_rings: int, per_ring: int, elevation_deg: float) -> np.ndarray:
    """The sensor positions of `elevation_rings` at one elevation, worked out here (0.5 m from the origin; alternate
    rings offset by half a step), unchecked."""
    e = np.radians(elevation_deg)
    ring, k = np.meshgrid(np.arange(n_rings), np.arange(per_ring), indexing="ij")
    a = 2 * np.pi * (k + 0.5 * (ring % 2)).ravel() / per_ring
    eyes = 0.5 * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.full_like(a, np.sin(e))], axis=-1)
    return eyes + 0.0  # -0.0 and 0.0 are one position
