"""The workspace check every move must pass before the arm goes: where the flange, the sensor and the bracket between
them may be, and which straight moves may carry them there.

What is checked (all in the base frame, metres; limits are the [arm] keys):
- the *capsule* from the flange (TCP) to the sensor (TCP x hand_eye), of radius `bracket_radius_m`, lies inside the
  box workspace_min..workspace_max, outside the sphere of radius `min_reach_m` around the base origin and outside
  the cylinder of radius `keepout_radius_m` around the base's vertical axis (the arm's own column);
- the flange is no further than `max_reach_m` from the base origin;
- every straight move (moveL: the TCP on a straight line, its rotation turning about one axis) keeps the same capsule
  out of both keep-outs and inside the box all the way, from the arm's position before the move where it is known.
  The flange's straight path is checked exactly; the sensor and bracket, whose path curves as the tool turns, at
  samples no more than MOVE_STEP_M / MOVE_STEP_RAD apart.
A failure is one ConfigError line naming the first bad pose or move and the limit it breaks.
"""

from __future__ import annotations

import math

import numpy as np

from spadscan.protocol.errors import ConfigError

from .arm.pose_convert import matrix_to_rotvec
from .config import ArmConfig

MOVE_STEP_M = 0.005
"""Largest translation between two samples of a straight move (m)."""
MOVE_STEP_RAD = 0.02
"""Largest rotation between two samples of a straight move (rad): 2 mm at a sensor 10 cm from the flange."""


def check_workspace(tcp_poses: np.ndarray, arm: ArmConfig, where: str, start: np.ndarray | None = None,
                    first: int = 0, of: int | None = None) -> None:
    """Raise ConfigError naming the first TCP pose (P, 4, 4) or straight move that leaves the workspace; `start`
    (4, 4), when given, is where the arm is before the first move. `first`: the plan's number of the first pose given
    (the poses a scan has left are the rest of a plan of first + P), so that the message names the plan's pose; `of`:
    the plan's length, when the poses given end before it (default first + P)."""
    tcp = np.asarray(tcp_poses, dtype=np.float64)
    n = len(tcp)
    if n == 0:
        return
    total = first + n if of is None else of
    pos = tcp[:, :3, 3]
    if not np.all(np.isfinite(tcp)):
        i = int(np.flatnonzero(~np.isfinite(tcp).all(axis=(1, 2)))[0])
        raise ConfigError(f"{where}: pose {first + i} of {total}: TCP position is not finite")
    for i in range(n):
        reason = _pose_problem(tcp[i], arm)
        if reason:
            p = ", ".join(f"{v:.3f}" for v in pos[i])
            raise ConfigError(f"{where}: pose {first + i} of {total}: TCP at [{p}] m is unreachable: {reason} "
                              f"([arm] limits)")
    moves = [(j - 1, j) for j in range(1, n)]
    poses = tcp
    if start is not None:
        reason = _pose_problem(np.asarray(start, dtype=np.float64), arm)
        if reason:  # not the move's fault: the arm already stands outside (jogged, or at rest above the box)
            raise ConfigError(f"{where}: the arm stands where it may not: {reason} ([arm] limits); jog it into the "
                              f"workspace")
        poses = np.concatenate([np.asarray(start, dtype=np.float64)[None], tcp])
        moves = [(j, j + 1) for j in range(n)]
    for a, b in moves:
        reason = move_problem(poses[a], poses[b], arm)
        if reason:
            j = b - 1 if start is not None else b
            raise ConfigError(f"{where}: the straight move to pose {first + j} of {total} {reason} ([arm] limits)")


def first_move_problem(current: np.ndarray, target: np.ndarray, arm: ArmConfig) -> str | None:
    """Why the arm, found at TCP pose `current` (4, 4) before the first move of a run (a resume: the arm may have been
    jogged anywhere meanwhile), may not go straight to `target`, or None. The planned segments were checked when the
    scan was planned; this one exists only now."""
    problem = _pose_problem(current, arm)
    if problem:
        return f"it stands where it may not: {problem}"
    problem = move_problem(current, target, arm)
    return f"the straight move there {problem}" if problem else None


def move_problem(a: np.ndarray, b: np.ndarray, arm: ArmConfig) -> str | None:
    """Why the straight move from TCP pose a to b (4, 4) is unsafe ('passes 0.144 m from the base, inside
    min_reach_m 0.2', ...), or None."""
    ab = b[:3, 3] - a[:3, 3]
    d = float(np.linalg.norm(a[:3, 3] + _closest_t(a[:3, 3], ab) * ab))
    if arm.min_reach_m > 0 and d < arm.min_reach_m:  # the flange's own straight line, exactly
        return f"passes {d:.3f} m from the base, inside min_reach_m {arm.min_reach_m}"
    r = arm.bracket_radius_m
    flange, sensor = _move_samples(a, b, arm.hand_eye)
    what = "the sensor" if np.any(sensor != flange) else "the TCP"
    dist = _segment_point_distance(flange, sensor, np.zeros(3)) - r
    if arm.min_reach_m > 0 and dist.min() < arm.min_reach_m:
        return f"brings {what} {dist.min():.3f} m{_bracket(r)} from the base, inside min_reach_m {arm.min_reach_m}"
    if arm.keepout_radius_m > 0:
        axis = _segment_axis_distance(flange, sensor) - r
        if axis.min() < arm.keepout_radius_m:
            return (f"brings {what} {axis.min():.3f} m{_bracket(r)} from the base's vertical axis, inside "
                    f"keepout_radius_m {arm.keepout_radius_m}")
    if arm.workspace_min is not None:
        for point, label in ((flange, "TCP"), (sensor, "sensor")):
            out = _box_problem(point, arm, r)
            if out:
                return f"takes the {label} out of the workspace: {out}"
    return None


def _pose_problem(tcp: np.ndarray, arm: ArmConfig) -> str | None:
    """Why one TCP pose (4, 4) is unsafe, or None."""
    flange = tcp[:3, 3]
    sensor = (tcp @ arm.hand_eye)[:3, 3]
    r = arm.bracket_radius_m
    if arm.workspace_min is not None:
        out = _box_problem(flange[None], arm, r)
        if out:
            return out
        out = _box_problem(sensor[None], arm, r)
        if out:
            return f"the sensor (TCP x hand_eye) is outside the workspace: {out}"
    reach = float(np.linalg.norm(flange))
    if reach < arm.min_reach_m:
        return f"its distance {reach:.3f} m from the base is below min_reach_m {arm.min_reach_m}"
    near = float(_segment_point_distance(flange[None], sensor[None], np.zeros(3))[0]) - r
    if near < arm.min_reach_m:
        return (f"the sensor or its bracket comes {near:.3f} m{_bracket(r)} from the base, below min_reach_m "
                f"{arm.min_reach_m}")
    if arm.keepout_radius_m > 0:
        axis = float(_segment_axis_distance(flange[None], sensor[None])[0]) - r
        if axis < arm.keepout_radius_m:
            return (f"it comes {axis:.3f} m{_bracket(r)} from the base's vertical axis, inside keepout_radius_m "
                    f"{arm.keepout_radius_m}")
    if arm.max_reach_m is not None and reach > arm.max_reach_m:
        return f"its distance {reach:.3f} m from the base exceeds max_reach_m {arm.max_reach_m}"
    return None


def _box_problem(points: np.ndarray, arm: ArmConfig, margin: float) -> str | None:
    """The first point (k, 3) outside the box shrunk by `margin` on every side, described, or None."""
    lo, hi = arm.workspace_min + margin, arm.workspace_max - margin
    bad = (points < lo) | (points > hi)
    if not bad.any():
        return None
    k, axis = (int(v[0]) for v in np.nonzero(bad))
    v = points[k, axis]
    low = v < lo[axis]
    side, limit = ("below workspace_min", arm.workspace_min[axis]) if low else \
        ("above workspace_max", arm.workspace_max[axis])
    # The bracket keeps bracket_radius_m inside the box: on the low side the limit rises by it, on the high side
    # it falls; the operator jogging the arm needs the limit itself.
    extra = (f" {'plus' if low else 'less'} bracket_radius_m {margin:g} = {(lo if low else hi)[axis]:.3f} m"
             if margin > 0 else "")
    return f"{'xyz'[axis]} = {v:.3f} m is {side} {limit:.3f} m{extra}"


def _bracket(r: float) -> str:
    return f" (less bracket_radius_m {r:g})" if r > 0 else ""


def _move_samples(a: np.ndarray, b: np.ndarray, hand_eye: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flange and sensor positions (k, 3) along the straight move a -> b, ends included."""
    turn = matrix_to_rotvec(a[:3, :3].T @ b[:3, :3])
    k = 1 + max(1, math.ceil(max(np.linalg.norm(b[:3, 3] - a[:3, 3]) / MOVE_STEP_M,
                                 np.linalg.norm(turn) / MOVE_STEP_RAD)))
    s = np.linspace(0.0, 1.0, k)
    flange = a[:3, 3] + s[:, None] * (b[:3, 3] - a[:3, 3])
    offset = hand_eye[:3, 3]
    # The tool turns about one fixed axis (turn's direction) by s x its angle: Rodrigues' formula applied to the one
    # vector `offset` for every sample at once (a 2,000-pose plan has 300,000 samples: a matrix each took seconds).
    angle = float(np.linalg.norm(turn))
    if angle < 1e-12:
        turned = np.broadcast_to(offset, (k, 3))
    else:
        axis = turn / angle
        phi = s[:, None] * angle
        turned = (offset * np.cos(phi) + np.cross(axis, offset) * np.sin(phi)
                  + axis * float(axis @ offset) * (1.0 - np.cos(phi)))
    sensor = flange + turned @ a[:3, :3].T
    return flange, sensor


def _closest_t(a: np.ndarray, ab: np.ndarray) -> float:
    """Parameter in [0, 1] of the point of segment a + t ab nearest the origin."""
    return float(np.clip(-np.dot(a, ab) / max(np.dot(ab, ab), 1e-300), 0.0, 1.0))


def _segment_point_distance(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Distance from point p (3,) to each segment a[i]-b[i] (k, 3) -> (k,)."""
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * ab - p, axis=1)


def _segment_axis_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Horizontal distance from the base's vertical axis (x = y = 0) to each segment a[i]-b[i] (k, 3) -> (k,)."""
    flat = np.zeros((len(a), 3))
    a2, b2 = a.copy(), b.copy()
    a2[:, 2] = b2[:, 2] = 0.0
    return _segment_point_distance(a2, b2, flat[0])
