"""Scan plans: the sensor poses of a scan, their visiting order, the TCP poses that carry the sensor there, checked
against the workspace (`workspace.py`) before the first move.

Poses are (P, 4, 4) float64, metres, in the arm's base frame; the sensor looks along its local +z. The hand-eye
transform X (tool flange -> sensor) links them: sensor pose = TCP pose @ X, so TCP pose = sensor pose @ inv(X).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spadscan.protocol.errors import ConfigError, SimulationError
from spadscan.protocol.next_views import CANDIDATES

from .config import ArmConfig, ScanConfig, scan_to_dict
from .workspace import check_workspace


@dataclass
class ScanPlan:
    """sensor_poses, tcp_poses: (P, 4, 4) in visiting order; description: JSON-able record of how it was made."""

    sensor_poses: np.ndarray
    tcp_poses: np.ndarray
    description: dict

    def __len__(self) -> int:
        return len(self.sensor_poses)


def invert_rigid(m: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (4, 4) or a stack (n, 4, 4)."""
    m = np.asarray(m, dtype=np.float64)
    out = np.zeros_like(m)
    rt = np.swapaxes(m[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, m[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def tcp_from_sensor(sensor_poses: np.ndarray, hand_eye: np.ndarray) -> np.ndarray:
    """TCP poses (P, 4, 4) that put the sensor at sensor_poses: sensor @ inv(hand_eye)."""
    return np.asarray(sensor_poses, dtype=np.float64) @ invert_rigid(hand_eye)


def sensor_from_tcp(tcp_poses: np.ndarray, hand_eye: np.ndarray) -> np.ndarray:
    """Sensor poses (..., 4, 4) of the TCP poses: tcp @ hand_eye."""
    return np.asarray(tcp_poses, dtype=np.float64) @ np.asarray(hand_eye, dtype=np.float64)


def generate_sensor_poses(scan: ScanConfig, where: str = "scan") -> np.ndarray:
    """The schedule's sensor poses (views, 4, 4) in generated order, jittered when scan.jitter_deg > 0. `where`
    begins a refusal's line (`config.check_scan` refuses, naming the keys, every scan config it knows to fail here)."""
    from spadscan.protocol import schedules

    try:
        if scan.schedule in ("fibonacci", "adaptive"):  # adaptive: its fallback plan
            poses = schedules.fibonacci_hemisphere(scan.views, scan.radius_m, scan.target, scan.min_elevation_deg,
                                                   scan.max_elevation_deg)
        else:
            poses = schedules.elevation_rings(scan.rings, scan.views // scan.rings, scan.radius_m, scan.target,
                                              scan.min_elevation_deg, scan.max_elevation_deg)
        if scan.jitter_deg > 0:
            poses = schedules.jitter_orientations(poses, scan.jitter_deg, np.random.default_rng(scan.seed))
    except SimulationError as exc:
        raise ConfigError(f"{where}: schedule {scan.schedule!r}: {exc}") from None
    return poses


def _elevation_azimuth(positions: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = positions - target
    return np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])), np.arctan2(d[:, 1], d[:, 0])


def order_nearest(positions: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """Greedy nearest-neighbour tour over positions (P, 3); begins nearest `start` (3,), else at index 0.

    Returns a permutation (P,). O(P^2) arithmetic: ~0.3 s for 10,000 views.
    """
    n = len(positions)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    first = 0 if start is None else int(np.argmin(np.linalg.norm(positions - start, axis=1)))
    order = np.empty(n, dtype=np.int64)
    free = np.ones(n, dtype=bool)
    cur = first
    for k in range(n):
        order[k] = cur
        free[cur] = False
        if k + 1 < n:
            d = np.sum((positions - positions[cur]) ** 2, axis=1)
            d[~free] = np.inf
            cur = int(np.argmin(d))
    return order


def order_serpentine(positions: np.ndarray, target: np.ndarray, bands: int) -> np.ndarray:
    """Band by band from the highest elevation down, azimuth alternating in direction between bands.

    positions (P, 3), target (3,); `bands` elevation bands of equal count (the rings, for a ring schedule).
    """
    n = len(positions)
    elev, azim = _elevation_azimuth(positions, target)
    by_elev = np.argsort(-elev, kind="stable")
    order = []
    for b, idx in enumerate(np.array_split(by_elev, max(1, min(bands, n)))):
        idx = idx[np.argsort(azim[idx], kind="stable")]
        order.extend(idx[::-1] if b % 2 else idx)
    return np.asarray(order, dtype=np.int64)


def path_length(positions: np.ndarray) -> float:
    """Total straight-line travel (m) through positions (P, 3) in order."""
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()) if len(positions) > 1 else 0.0


def build_plan(scan: ScanConfig, arm: ArmConfig, *, start_tcp: np.ndarray | None = None,
               where: str = "scan") -> ScanPlan:
    """Generate, order and check a scan plan; start_tcp (4, 4) is where the arm is now, when known."""
    sensor = generate_sensor_poses(scan, where)
    tcp = tcp_from_sensor(sensor, arm.hand_eye)
    start = None if start_tcp is None else np.asarray(start_tcp, float)[:3, 3]
    pos = tcp[:, :3, 3]
    if scan.order == "nearest":
        if start is None:  # begin at the highest view: the arm usually waits above the object
            start = pos[int(np.argmax(_elevation_azimuth(sensor[:, :3, 3], scan.target)[0]))]
        perm = order_nearest(pos, start)
    elif scan.order == "serpentine":
        bands = scan.rings if scan.schedule == "rings" else max(1, round(math.sqrt(scan.views / 2)))
        perm = order_serpentine(sensor[:, :3, 3], np.asarray(scan.target, float), bands)
    else:
        perm = np.arange(len(sensor))
    extra = {}
    if scan.schedule == "adaptive":
        first = initial_first(sensor[perm], np.asarray(scan.target, float), scan.initial_views, tcp[perm])
        perm = perm[first]
        extra = {"candidates": CANDIDATES, "fallback": "fibonacci"}
    sensor, tcp = sensor[perm], tcp[perm]
    start = None if start_tcp is None else np.asarray(start_tcp, float)
    if scan.schedule == "adaptive":
        # Only the initial views are a path; every later move is checked when its pose is chosen.
        check_workspace(tcp[:scan.initial_views], arm, where, start)
        for k in range(scan.initial_views, len(tcp)):
            check_workspace(tcp[k:k + 1], arm, f"{where} pose {k}")
    else:
        check_workspace(tcp, arm, where, start)
    description = {**scan_to_dict(scan), **extra, "travel_m": round(path_length(tcp[:, :3, 3]), 4),
                   "generated_order": perm.tolist()}
    return ScanPlan(sensor, tcp, description)


def spread_subset(directions: np.ndarray, k: int, first: int = 0) -> np.ndarray:
    """Indices of k of the unit vectors (P, 3), each in turn the one farthest from all chosen so far (by angle),
    beginning with `first`: a well-spread subset, in the order chosen."""
    n = len(directions)
    k = min(k, n)
    chosen = [first]
    nearest = directions @ directions[first]  # cosine to the nearest chosen: smaller is farther
    for _ in range(1, k):
        nearest[chosen] = np.inf
        j = int(np.argmin(nearest))
        chosen.append(j)
        nearest = np.maximum(nearest, directions @ directions[j])
    return np.asarray(chosen, dtype=np.int64)


def initial_first(sensor: np.ndarray, target: np.ndarray, n_initial: int, tcp: np.ndarray) -> np.ndarray:
    """A permutation of a plan in visiting order (sensor and tcp (P, 4, 4)) that puts a well-spread subset of
    n_initial poses first (`spread_subset`, from the plan's first pose; visited by a nearest-neighbour tour from it),
    then the others by a nearest-neighbour tour from the last of them: an adaptive scan's initial views, then its
    fallback plan."""
    d = sensor[:, :3, 3] - target
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    initial = spread_subset(d, n_initial, 0)
    initial = initial[order_nearest(tcp[initial, :3, 3], tcp[0, :3, 3])]
    rest = np.setdiff1d(np.arange(len(sensor)), initial)
    rest = rest[order_nearest(tcp[rest, :3, 3], tcp[initial[-1], :3, 3])]  # a tour on from the last initial view
    return np.concatenate([initial, rest])
