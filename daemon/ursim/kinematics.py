"""Motion model of the simulated UR controller: fake kinematics, trapezoidal timing, interpolated moves.

The kinematics are deliberately fake. `inverse_kinematics` is an affine map of the pose vector
[x, y, z, rx, ry, rz] to six joint angles, q = M @ pose + q_home, and `forward_kinematics` its exact inverse: smooth,
deterministic and invertible everywhere (except where the rotation vector itself wraps at angle pi), which is all the
tests need from joint angles; it is not the geometry of any real arm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spadscan.daemon.arm.pose_convert import matrix_to_rotvec, rotvec_to_matrix

_M = 2.0 * np.eye(6) + 0.25 * np.eye(6, k=1) - 0.25 * np.eye(6, k=-1)
_M_INV = np.linalg.inv(_M)
Q_HOME = np.array([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])

ROTATION_RADIUS_M = 0.1
"""A linear move's path length counts rotation as the arc a point this far from the TCP travels."""

MIN_RATE = 1e-6
"""Speeds and accelerations below this (or non-finite) are clamped here, so a move always ends."""


SHOULDER_M = np.array([0.0, 0.0, 0.1625])
"""Where the reach is measured from (a UR5e's shoulder joint height above its base)."""
INNER_RADIUS_M = 0.05
"""No solution this close to the base's vertical axis (the wrist cannot stand on the column)."""


def reachable(pose_vec: np.ndarray, reach_m: float) -> bool:
    """Whether the controller would find an inverse kinematics solution for a TCP pose vector (6,): within reach_m
    of the shoulder and clear of the base's axis. A UR5e-sized envelope, not the geometry of any real arm."""
    p = np.asarray(pose_vec, dtype=np.float64)[:3]
    return bool(np.linalg.norm(p - SHOULDER_M) <= reach_m and np.hypot(p[0], p[1]) >= INNER_RADIUS_M)


def inverse_kinematics(pose_vec: np.ndarray) -> np.ndarray:
    """Fake IK: pose vector (6,) [m, rad] -> joint angles (6,) [rad]."""
    return _M @ np.asarray(pose_vec, dtype=np.float64) + Q_HOME


def forward_kinematics(q: np.ndarray) -> np.ndarray:
    """Inverse of `inverse_kinematics`: joint angles (6,) [rad] -> pose vector (6,) [m, rad]."""
    return _M_INV @ (np.asarray(q, dtype=np.float64) - Q_HOME)


def _rate(x: float) -> float:
    return x if math.isfinite(x) and x > MIN_RATE else MIN_RATE


def profile_duration(distance: float, speed: float, accel: float) -> float:
    """Seconds a trapezoidal (or triangular) velocity profile takes to cover `distance` from rest to rest."""
    v, a = _rate(speed), _rate(accel)
    if distance <= 0.0:
        return 0.0
    if distance > v * v / a:
        return distance / v + v / a
    return 2.0 * math.sqrt(distance / a)


def profile_fraction(t: float, duration: float) -> float:
    """Fraction (0..1) of the path covered at time t of a rest-to-rest move (smooth cubic ease, monotonic)."""
    if duration <= 0.0 or t >= duration:
        return 1.0
    if t <= 0.0:
        return 0.0
    u = t / duration
    return u * u * (3.0 - 2.0 * u)


@dataclass
class Motion:
    """One move in progress. Linear moves interpolate the pose (straight line, shortest rotation); joint moves the
    joint angles. Times are controller seconds (already scaled by the controller's time scale)."""

    linear: bool
    start: np.ndarray
    """(6,) pose vector for linear moves, joint angles for joint moves."""
    goal: np.ndarray
    t_start: float
    duration: float

    @classmethod
    def plan(cls, linear: bool, start_pose: np.ndarray, goal: np.ndarray, speed: float, accel: float,
             t_start: float, time_scale: float) -> Motion:
        """Plan from the current pose vector (6,) to `goal` (pose vector if linear, else joint angles)."""
        start_pose = np.asarray(start_pose, dtype=np.float64)
        goal = np.asarray(goal, dtype=np.float64)
        if linear:
            rot = rotvec_to_matrix(start_pose[3:]).T @ rotvec_to_matrix(goal[3:])
            dist = max(float(np.linalg.norm(goal[:3] - start_pose[:3])),
                       ROTATION_RADIUS_M * float(np.linalg.norm(matrix_to_rotvec(rot))))
            start = start_pose
        else:
            start = inverse_kinematics(start_pose)
            dist = float(np.abs(goal - start).max())
        return cls(linear, start, goal, t_start, time_scale * profile_duration(dist, speed, accel))

    def end_time(self) -> float:
        return self.t_start + self.duration

    def pose_at(self, t: float) -> np.ndarray:
        """Pose vector (6,) at controller time t."""
        u = profile_fraction(t - self.t_start, self.duration)
        if not self.linear:
            return forward_kinematics(self.start + u * (self.goal - self.start))
        r0 = rotvec_to_matrix(self.start[3:])
        rel = matrix_to_rotvec(r0.T @ rotvec_to_matrix(self.goal[3:]))
        pos = self.start[:3] + u * (self.goal[:3] - self.start[:3])
        return np.concatenate([pos, matrix_to_rotvec(r0 @ rotvec_to_matrix(u * rel))])
