"""Where the zones looked: zone axes and edges, and the box around everything the first returns saw (metres)."""

from __future__ import annotations

import math

import numpy as np

from spadscan.protocol.errors import CaptureError
from spadscan.protocol.sensor_model import SensorModel, Zone

from .returns import FirstReturns


def zone_axis(zone: Zone) -> np.ndarray:
    """(3,) unit vector in the sensor frame: a cone's axis, or the direction to a rect zone's centre."""
    if zone.kind == "cone":
        a = np.asarray(zone.axis, float)
    else:
        a = np.array([0.5 * (zone.tan_x[0] + zone.tan_x[1]), 0.5 * (zone.tan_y[0] + zone.tan_y[1]), 1.0])
    return a / np.linalg.norm(a)


def zone_edges(zone: Zone, n: int = 8) -> np.ndarray:
    """(m, 3) unit directions on the edge of a zone's field of view, plus its axis (sensor frame)."""
    if zone.kind == "cone":
        a = zone_axis(zone)
        u = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        v = np.cross(a, u)
        phi = np.linspace(0, 2 * np.pi, n, endpoint=False)[:, None]
        c, s = math.cos(zone.half_angle_rad), math.sin(zone.half_angle_rad)
        dirs = c * a + s * (np.cos(phi) * u + np.sin(phi) * v)
    else:
        dirs = np.array([[x, y, 1.0] for x in zone.tan_x for y in zone.tan_y])
    dirs = np.vstack([dirs, zone_axis(zone)])
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def scene_bounds(returns: FirstReturns, poses: np.ndarray, sensor: SensorModel, *, pad: float = 0.1,
                 floor_z: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A box (min (3,), max (3,), metres) around everything the zones saw: the footprints of the first returns.

    Each detected zone contributes its field of view's edge and axis directions at its first return's range; the box
    is grown by `pad` times its size on every side. Raises CaptureError when no zone saw anything.
    """
    rng = returns.arrival_range_m(sensor)
    pts = []
    for z, zone in enumerate(sensor.zones):
        ok = returns.detected[:, z]
        if not ok.any():
            continue
        dirs = zone_edges(zone)  # (m, 3)
        world = np.einsum("nij,mj->nmi", poses[ok, :3, :3], dirs)  # (k, m, 3)
        pts.append((poses[ok, None, :3, 3] + world * rng[ok, z, None, None]).reshape(-1, 3))
    if not pts:
        raise CaptureError("no histogram holds a return above the threshold: nothing to reconstruct")
    allp = np.concatenate(pts)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    size = np.maximum(hi - lo, 1e-3)
    lo, hi = lo - pad * size, hi + pad * size
    if floor_z is not None:
        lo[2] = max(lo[2], floor_z - 0.02 * size[2])
        if hi[2] <= lo[2]:
            raise CaptureError(f"every return lies below the floor z = {floor_z} m")
    return lo, hi


def cube_around(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smallest cube with the same centre that holds the box (cubic voxels on an R^3 grid)."""
    c, half = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo))
    return c - half, c + half


__all__ = ["zone_axis", "zone_edges", "scene_bounds", "cube_around"]
