"""Pose schedules: where the sensor goes. Poses are (n, 4, 4) sensor-to-world transforms in metres; the sensor looks
along its local +z axis. Angles are degrees at this module's edge (they come from the user) and radians inside.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import SimulationError

GOLDEN_ANGLE_RAD = math.pi * (3.0 - math.sqrt(5.0))


def _vec3(v, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise SimulationError(f"{what} must be 3 finite numbers, got {v!r}")
    return a


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Pose (4, 4) of a sensor at `eye` whose +z looks at `target`; its +y is `up` projected off the view axis.

    When the view axis is (anti)parallel to `up` (looking straight down), world +y stands in for `up`, so the pose is
    still well defined.
    """
    eye, target, up = _vec3(eye, "eye"), _vec3(target, "target"), _vec3(up, "up")
    z = target - eye
    dist = np.linalg.norm(z)
    if dist < 1e-9:
        raise SimulationError(f"eye and target coincide at {eye.tolist()} m: no view direction")
    z /= dist
    y = up - (up @ z) * z
    if np.linalg.norm(y) < 1e-6 * max(np.linalg.norm(up), 1e-300):
        alt = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        y = alt - (alt @ z) * z
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
    return pose


def _check_elevations(lo: float, hi: float) -> tuple[float, float]:
    if not (math.isfinite(lo) and math.isfinite(hi) and -90.0 <= lo <= hi <= 90.0):
        raise SimulationError(f"elevation range [{lo}, {hi}] deg must satisfy -90 <= min <= max <= 90")
    return math.radians(lo), math.radians(hi)


def _check_radius(radius_m: float) -> float:
    if not (math.isfinite(radius_m) and radius_m > 0):
        raise SimulationError(f"radius {radius_m} m must be finite and > 0")
    return float(radius_m)


def _poses_on_sphere(elev: np.ndarray, azim: np.ndarray, radius_m: float, target) -> np.ndarray:
    target = _vec3(target, "target")
    ce = np.cos(elev)
    eyes = target + radius_m * np.stack([ce * np.cos(azim), ce * np.sin(azim), np.sin(elev)], axis=-1)
    return np.stack([look_at(e, target) for e in eyes]) if len(eyes) else np.zeros((0, 4, 4))


def fibonacci_hemisphere(n: int, radius_m: float, target=(0.0, 0.0, 0.0), min_elevation_deg: float = 0.0,
                         max_elevation_deg: float = 86.0) -> np.ndarray:
    """n poses on a Fibonacci spiral, equal area per view, from the top down, all looking at `target`.

    The band between the two elevations is cut into n strips of equal area (equal steps in sin(elevation)); view i
    sits at the middle of strip i at azimuth (i + 1/2) x golden angle. LCSPCData's simulated scenes are exactly
    `fibonacci_hemisphere(256, 0.5, max_elevation_deg=90)` (views from 86.4 down to 0.1 deg). Returns (n, 4, 4).
    """
    if not (isinstance(n, (int, np.integer)) and 1 <= n <= 1_000_000):
        raise SimulationError(f"number of views {n} must be an integer in [1, 1000000]")
    lo, hi = _check_elevations(min_elevation_deg, max_elevation_deg)
    radius_m = _check_radius(radius_m)
    pole = spiral_at_pole_deg(n, min_elevation_deg, max_elevation_deg)
    if pole is not None:
        raise SimulationError(f"a spiral band of zero width at {pole:+g} deg elevation puts its {n} views at one "
                              f"viewpoint (straight {'above' if pole > 0 else 'below'} the target); widen the band "
                              f"(min_elevation below max_elevation, degrees)")
    i = np.arange(n) + 0.5
    s = math.sin(hi) - i / n * (math.sin(hi) - math.sin(lo))
    return _poses_on_sphere(np.arcsin(np.clip(s, -1, 1)), i * GOLDEN_ANGLE_RAD, radius_m, target)


def spiral_at_pole_deg(n: int, min_elevation_deg: float, max_elevation_deg: float) -> float | None:
    """The elevation (degrees) of a spiral band of zero width at +-90 deg holding several views, or None. Every view
    of it stands at one point: n copies of one viewpoint. (A band of zero width elsewhere is a circle the golden
    angle never repeats on, and any wider band gives each view its own elevation.)"""
    if n < 2 or min_elevation_deg != max_elevation_deg or abs(min_elevation_deg) < 90.0:
        return None
    return float(min_elevation_deg)


RINGS_BAND_DEG = (10.0, 80.0)
"""The rings' own band of elevations (degrees, lowest and highest ring): rings stand at both ends of a band, so the
spiral's 0-90 deg would put a whole ring at the zenith, every view of it from one position."""
MAX_VIEWS_PER_RING = 100_000
"""Most views one ring may hold (`elevation_rings`)."""


def ring_elevations_rad(n_rings: int, lo_rad: float, hi_rad: float) -> np.ndarray:
    """The rings' elevations (radians): at both ends of the band and evenly between; one ring stands midway."""
    return np.linspace(lo_rad, hi_rad, n_rings) if n_rings > 1 else np.array([(lo_rad + hi_rad) / 2])


def ring_at_pole_deg(n_rings: int, per_ring: int, min_elevation_deg: float, max_elevation_deg: float) -> float | None:
    """The elevation (degrees) of a ring of several views at +-90 deg, or None. Every view of such a ring stands at
    one point: per_ring copies of one viewpoint, not a ring. The schedule and the daemon's config refuse it alike."""
    if per_ring < 2:
        return None
    elev = ring_elevations_rad(n_rings, math.radians(min_elevation_deg), math.radians(max_elevation_deg))
    pole = elev[np.abs(elev) >= math.pi / 2 - 1e-9]
    return float(math.degrees(pole[-1])) if len(pole) else None


def rings_repeat_note(n_rings: int, min_elevation_deg: float, max_elevation_deg: float) -> str | None:
    """Why rings in a band of zero width put two views on one pose (a clause for a refusal), or None when no pose
    repeats. Such rings all stand at the band's one elevation, and alternate rings are offset by half a step, no
    more: ring 3 stands on ring 1's poses, while 2 rings are one ring of twice the views. At +-90 deg, where the
    azimuth moves no view, 2 rings already stand at one point. (A ring of several views at a pole is
    `ring_at_pole_deg`'s.)"""
    if n_rings < 2 or min_elevation_deg != max_elevation_deg:
        return None
    if abs(min_elevation_deg) >= 90.0:
        return (f"{n_rings} rings in a band of zero width at {min_elevation_deg:+g} deg elevation all stand at one "
                f"viewpoint (straight {'above' if min_elevation_deg > 0 else 'below'} the target)")
    if n_rings > 2:
        return (f"{n_rings} rings in a band of zero width ({min_elevation_deg:g} deg) all stand at one elevation, "
                f"every other ring on the same poses")
    return None


def elevation_rings(n_rings: int, per_ring: int, radius_m: float, target=(0.0, 0.0, 0.0),
                    min_elevation_deg: float = RINGS_BAND_DEG[0],
                    max_elevation_deg: float = RINGS_BAND_DEG[1]) -> np.ndarray:
    """Rings of equally spaced views at evenly spaced elevations (inclusive), alternate rings offset by half a step.

    Returns (n_rings * per_ring, 4, 4), ring by ring from the lowest elevation, azimuth increasing within a ring.
    A ring of more than one view at +-90 deg (every view at one point) is refused, and so are several rings in a band
    of zero width: they all stand at one elevation, and from 3 rings on every other ring stands on the same poses
    (`rings_repeat_note`). 2 such rings repeat no pose (one ring of twice the views, `spadscan simulate` renders
    them), but are refused here all the same: the daemon's config allows a band of zero width for one ring only,
    and the plans it checks are built here by the same rule.
    """
    for name, v in (("rings", n_rings), ("views per ring", per_ring)):
        if not (isinstance(v, (int, np.integer)) and 1 <= v <= MAX_VIEWS_PER_RING):
            raise SimulationError(f"{name} {v} must be an integer in [1, {MAX_VIEWS_PER_RING}]")
    lo, hi = _check_elevations(min_elevation_deg, max_elevation_deg)
    radius_m = _check_radius(radius_m)
    if n_rings > 1 and min_elevation_deg == max_elevation_deg:
        same = ", every other ring on the same poses" if n_rings > 2 else ""
        raise SimulationError(f"{n_rings} rings in a band of zero width ({min_elevation_deg:g} deg) all stand at one "
                              f"elevation{same}; widen the band (min_elevation below max_elevation, degrees) or use "
                              f"one ring")
    elev = ring_elevations_rad(n_rings, lo, hi)
    pole = ring_at_pole_deg(n_rings, per_ring, min_elevation_deg, max_elevation_deg)
    if pole is not None:
        where = "max_elevation" if pole > 0 else "min_elevation"
        raise SimulationError(f"a ring at {pole:+g} deg elevation puts its {per_ring} views "
                              f"at one viewpoint (straight {'above' if pole > 0 else 'below'} the "
                              f"target); keep {where} strictly between -90 and 90 deg")
    ring, k = np.meshgrid(np.arange(n_rings), np.arange(per_ring), indexing="ij")
    azim = 2 * math.pi * (k + 0.5 * (ring % 2)) / per_ring
    return _poses_on_sphere(elev[ring.ravel()], azim.ravel(), radius_m, target)


def turned_about_vertical(poses: np.ndarray, angle_rad: float, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Poses (n, 4, 4) turned by `angle_rad` about the vertical (world z) through `target`.

    A ring from `elevation_rings` turned so is the same ring at azimuths shifted by the angle: its views look at the
    target still, with world z as their `up`, which the turn leaves in place.
    """
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    turn = np.eye(4)
    turn[:2, :2] = [[c, -s], [s, c]]
    turn[:3, 3] = _vec3(target, "target") - turn[:3, :3] @ _vec3(target, "target")
    return turn @ poses


def random_rotations(n: int, max_deg: float, rng: np.random.Generator) -> np.ndarray:
    """n rotations (n, 3, 3) about axes uniform on the sphere by angles uniform in [0, max_deg]."""
    if not (math.isfinite(max_deg) and 0.0 <= max_deg <= 180.0):
        raise SimulationError(f"jitter {max_deg} deg must lie in [0, 180]")
    axis = rng.normal(size=(n, 3))
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    ang = rng.uniform(0.0, math.radians(max_deg), size=n)
    k = np.zeros((n, 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k -= k.transpose(0, 2, 1)
    s, c = np.sin(ang)[:, None, None], np.cos(ang)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def jitter_orientations(poses, max_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Turn each pose (n, 4, 4) about its own sensor origin by a random rotation of at most `max_deg` degrees.

    Like LCSPCData's `_random` captures: the sensor stays where it was but no longer looks exactly at the target.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise SimulationError(f"poses must have shape (n, 4, 4), got {poses.shape}")
    out = poses.copy()
    out[:, :3, :3] = poses[:, :3, :3] @ random_rotations(len(poses), max_deg, rng)
    return out
