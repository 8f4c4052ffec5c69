"""Where the zones looked: zone axes and edges, and the box around everything the first returns saw (metres)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spadscan.protocol.errors import CaptureError
from spadscan.protocol.mesh_io import MAX_EXTENT_M
from spadscan.protocol.sensor_model import SensorModel, Zone

from .returns import DEFAULT_THRESHOLD, FirstReturns, first_returns

RADIUS_FRACTION_MAX = 0.8
"""A scene's sphere never reaches closer to a sensor than this fraction of its distance to the sphere's centre."""
def given_sphere(scene: dict, where) -> tuple[np.ndarray | None, float | None]:
    """(centre (3,), radius m) of the sphere a capture's scene record gives, each None where it gives none;
    CaptureError naming `where` for a centre that is no finite 3-vector or a radius that is no positive number, or
    either beyond MAX_EXTENT_M (a radius of 1e300 made the grid's box NaN, refused by a message that named neither)."""
    center = radius = None
    if "center" in scene:
        try:
            center = np.asarray(scene["center"], dtype=float)
        except (TypeError, ValueError):
            center = None
        if center is None or center.shape != (3,) or not np.all(np.isfinite(center)):
            raise CaptureError(f"{where}: scene center {scene['center']} is not a finite 3-vector")
        if np.abs(center).max() > MAX_EXTENT_M:
            raise CaptureError(f"{where}: scene center {scene['center']} lies over {MAX_EXTENT_M:g} m from the "
                               f"origin (metres are meant)")
    if "radius" in scene:
        value = scene["radius"]
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0
        if not ok or value > MAX_EXTENT_M:
            raise CaptureError(f"{where}: scene radius {value} must be a positive number of metres, at most "
                               f"{MAX_EXTENT_M:g}")
        radius = float(value)
    return center, radius


BELOW_FLOOR_M = 0.005
"""A first return comes from clearly below a floor when the whole of its zone's field of view lies more than this
(or two bins, where that is more) under the floor at its range."""
BELOW_FLOOR_SHARE = 0.01
"""More than this share of the first returns from below a floor (and at least BELOW_FLOOR_MIN of them): the floor
cuts the object (a share, not one return: one view's noise can clear the threshold far away)."""
BELOW_FLOOR_MIN = 2


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


def returns_span(returns: FirstReturns, poses: np.ndarray, sensor: SensorModel,
                 share: float = 0.01) -> tuple[np.ndarray, np.ndarray] | None:
    """The box (min (3,), max (3,), metres) the first returns in front of the sensors lie in: each detected zone's
    field-of-view edges and axis at its first return's range (as `scene_bounds` takes them), the box between the
    `share` and 1 - `share` quantiles on each axis, so that a few returns of noise far off do not stretch it. None
    when no zone saw anything. What the returns support: a carved hull far wider than it is space no return holds."""
    rng = returns.arrival_range_m(sensor)
    pts = []
    for z, zone in enumerate(sensor.zones):
        ok = returns.detected[:, z] & (rng[:, z] > 0)  # NaN (nothing detected) compares False
        if ok.any():
            world = np.einsum("nij,mj->nmi", poses[ok, :3, :3], zone_edges(zone))
            pts.append((poses[ok, None, :3, 3] + world * rng[ok, z, None, None]).reshape(-1, 3))
    if not pts:
        return None
    allp = np.concatenate(pts)
    return np.quantile(allp, share, axis=0), np.quantile(allp, 1 - share, axis=0)


@dataclass(frozen=True)
class BelowFloor:
    """First returns that can only have come from below a floor: `below` of the `returns` detected, the lowest
    `depth_m` metres under it (its zone's highest point at its range; 0 when there is none)."""

    below: int
    returns: int
    depth_m: float = 0.0

    @property
    def cuts(self) -> bool:
        """Whether enough of them lie below for the floor to cut the object (BELOW_FLOOR_SHARE, BELOW_FLOOR_MIN)."""
        return self.below >= BELOW_FLOOR_MIN and self.below > BELOW_FLOOR_SHARE * self.returns

    def text(self) -> str:
        """'5 of 48 first returns come from wholly below it (up to 55 mm under it)'."""
        return (f"{self.below} of {self.returns} first returns come from wholly below it (up to "
                f"{self.depth_m * 1e3:.0f} mm under it)")


def zone_top_z(zone: Zone, rotations: np.ndarray) -> np.ndarray:
    """(n,) the largest world z component of a direction in `zone`'s field of view, for sensor-to-world rotations
    (n, 3, 3): exact for a cone (its axis's elevation plus its half angle), the edges' for a rect zone."""
    if zone.kind == "cone":
        axis_z = np.clip(rotations[:, 2, :] @ zone_axis(zone), -1.0, 1.0)
        return np.sin(np.minimum(np.arcsin(axis_z) + zone.half_angle_rad, 0.5 * np.pi))
    t = np.linspace(0.0, 1.0, 9)
    (x0, x1), (y0, y1) = zone.tan_x, zone.tan_y
    xs, ys = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
    edge = np.concatenate([np.stack([xs, np.full_like(xs, y), np.ones_like(xs)], 1) for y in (y0, y1)]
                          + [np.stack([np.full_like(ys, x), ys, np.ones_like(ys)], 1) for x in (x0, x1)])
    edge /= np.linalg.norm(edge, axis=1, keepdims=True)
    return (rotations[:, 2, :] @ edge.T).max(axis=1)


def returns_below_floor(hists, poses: np.ndarray, sensor: SensorModel, floor_z: float,
                        usable: np.ndarray | None = None) -> BelowFloor:
    """How many histograms' first returns (at the default threshold; hists (n, zones, bins) as carving reads them,
    poses (n, 4, 4)) can only have come from below a floor at `floor_z` metres: their zone's whole field of view at
    their range lies clearly under it (BELOW_FLOOR_M). No surface there, and a fit or a carving bounded by the floor
    cannot hold the part of the object they saw. usable (n, zones) bool, or None: histograms that hold data."""
    returns = first_returns(hists, sensor, DEFAULT_THRESHOLD, "matched")
    found = returns.detected if usable is None else returns.detected & np.asarray(usable, bool)
    rng = returns.arrival_range_m(sensor)
    poses = np.asarray(poses, np.float64)
    margin = max(BELOW_FLOOR_M, 2.0 * sensor.bin_width_m)
    depth = np.full(found.shape, -np.inf)
    for z, zone in enumerate(sensor.zones):
        top = poses[:, 2, 3] + np.where(found[:, z], rng[:, z], 0.0) * zone_top_z(zone, poses[:, :3, :3])
        depth[:, z] = np.where(found[:, z], floor_z - top, -np.inf)
    below = depth > margin
    return BelowFloor(int(below.sum()), int(found.sum()), float(depth[below].max()) if below.any() else 0.0)


def mesh_share_below(mesh, floor_z: float) -> float:
    """Share of a mesh's surface area (trimesh, metres) clearly below `floor_z` (its faces' centres BELOW_FLOOR_M
    under it): of a ground truth, the part a floor there cuts off."""
    area = np.asarray(mesh.area_faces, np.float64)
    if not len(area) or area.sum() <= 0:
        return 0.0
    under = np.asarray(mesh.triangles_center, np.float64)[:, 2] < floor_z - BELOW_FLOOR_M
    return float(area[under].sum() / area.sum())


def floor_cut_note(floor_z: float, why: str, returns: BelowFloor | None, truth_share: float | None,
                   remedy: str) -> str | None:
    """One line saying that an assumed floor at `floor_z` metres (`why` it is there) cuts the object, with the
    evidence (first returns from below it; the ground truth's share of surface below it) and the `remedy`; None when
    there is no evidence. Everything under the floor is left out of the result, which would not say so."""
    evidence = []
    if returns is not None and returns.cuts:
        evidence.append(returns.text())
    if truth_share is not None and truth_share > BELOW_FLOOR_SHARE:
        evidence.append(f"{100 * truth_share:.0f} % of the ground truth's surface lies below it")
    if not evidence:
        return None
    return (f"the floor at z = {floor_z:.3f} m ({why}) cuts the object: {' and '.join(evidence)}, and nothing below "
            f"the floor is reconstructed; if the object does not stand on it, {remedy}")


def cube_around(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smallest cube with the same centre that holds the box (cubic voxels on an R^3 grid)."""
    c, half = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo))
    return c - half, c + half


__all__ = ["zone_axis", "zone_edges", "scene_bounds", "returns_span", "cube_around", "BelowFloor",
           "returns_below_floor", "zone_top_z", "mesh_share_below", "floor_cut_note", "BELOW_FLOOR_M",
           "BELOW_FLOOR_SHARE", "BELOW_FLOOR_MIN"]
