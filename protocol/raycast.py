"""Rays over a zone's field of view and first hits against a mesh.

A zone's rays are spread evenly over its field of view (stratified, jittered once by a seed) and carry solid-angle
weights that sum to the zone's solid angle, so that `sum(weight * f(direction))` estimates the integral of f over the
zone in steradians. Ray casting uses trimesh's intersector, embree's when `embreex` is importable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import SimulationError
from .sensor_model import Zone

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@dataclass(frozen=True)
class ZoneRays:
    """Directions in the sensor frame and their solid-angle weights for every zone.

    directions: (zones, R, 3) unit vectors (+z is the boresight); weights: (zones, R) steradians per ray, summing over
    R to each zone's solid angle.
    """

    directions: np.ndarray
    weights: np.ndarray

    @property
    def n_rays(self) -> int:
        return int(self.directions.shape[1])


def cone_rays(zone: Zone, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n directions uniform in solid angle over a cone: a Fibonacci spiral on the cap, jittered within its rings.

    Returns (directions (n, 3), weights (n,)) with equal weights summing to the cone's solid angle.
    """
    cos_a = math.cos(zone.half_angle_rad)
    # Equal-area strata in cos(theta); each ray sits at a random height within its own stratum.
    u = 1.0 - (np.arange(n) + rng.random(n)) / n * (1.0 - cos_a)
    phi = np.arange(n) * GOLDEN_ANGLE + rng.random() * 2 * math.pi
    s = np.sqrt(np.maximum(1.0 - u * u, 0.0))
    d = np.stack([s * np.cos(phi), s * np.sin(phi), u], axis=-1)
    d = _rotate_z_to(d, np.asarray(zone.axis, float))
    return d, np.full(n, zone.solid_angle_sr() / n)


def rect_rays(zone: Zone, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """About n directions on a jittered grid in tan space (x/z, y/z) over a rectangular zone.

    Weights are the solid angle of each grid cell, dx dy / (1 + x^2 + y^2)^1.5 at the jittered point, rescaled to sum
    to the zone's exact solid angle. Returns (directions (m, 3), weights (m,)) with m = nx * ny close to n.
    """
    (x0, x1), (y0, y1) = zone.tan_x, zone.tan_y
    aspect = (x1 - x0) / (y1 - y0)
    nx = max(1, int(round(math.sqrt(n * aspect))))
    ny = max(1, int(round(n / nx)))
    gx, gy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    x = x0 + (gx.ravel() + rng.random(nx * ny)) * (x1 - x0) / nx
    y = y0 + (gy.ravel() + rng.random(nx * ny)) * (y1 - y0) / ny
    q = 1.0 + x * x + y * y
    d = np.stack([x, y, np.ones_like(x)], axis=-1) / np.sqrt(q)[:, None]
    w = q ** -1.5
    return d, w * (zone.solid_angle_sr() / w.sum())


def zone_rays(zones, rays_per_zone: int, seed: int) -> ZoneRays:
    """Rays for every zone, the same count per zone (rectangular zones round to a grid). Deterministic for a seed."""
    if not (isinstance(rays_per_zone, (int, np.integer)) and 1 <= rays_per_zone <= 10_000_000):
        raise SimulationError(f"rays per zone {rays_per_zone} must be an integer in [1, 1e7]")
    rng = np.random.default_rng(seed)
    dirs, weights = [], []
    for zone in zones:
        d, w = (cone_rays if zone.kind == "cone" else rect_rays)(zone, int(rays_per_zone), rng)
        dirs.append(d)
        weights.append(w)
    # Rect grids may round differently: keep one count, rescale the weights. The rays kept are spread over the
    # whole grid: the first m alone (the grid runs x-major) left most of a zone's last column unsampled.
    m = min(len(w) for w in weights)
    keep = [np.round(np.linspace(0, len(w) - 1, m)).astype(int) for w in weights]
    dirs = [d[k] for d, k in zip(dirs, keep)]
    weights = [w[k] * (w.sum() / w[k].sum()) for w, k in zip(weights, keep)]
    return ZoneRays(np.stack(dirs), np.stack(weights))


def _rotate_z_to(d: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Rotate directions so that +z maps onto `axis` (unit), by the shortest rotation."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, axis)
    c = float(axis @ z)
    if np.linalg.norm(v) < 1e-12:
        return d if c > 0 else -d
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    rot = np.eye(3) + vx + vx @ vx / (1.0 + c)
    return d @ rot.T


RAY_CHUNK = 4096
"""Rays handed to the intersector at a time (bounds the memory of trimesh's own intersector)."""


def make_intersector(mesh):
    """The fastest ray intersector trimesh offers for this mesh (embree when importable, else trimesh's own)."""
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh)
    except Exception:  # embreex missing or failing to load: the pure-python intersector is slower but exact
        from trimesh.ray.ray_triangle import RayMeshIntersector

        return RayMeshIntersector(mesh)


def first_hits(intersector, mesh, origins: np.ndarray, directions: np.ndarray):
    """First surface hit along each ray.

    origins, directions: (N, 3) (directions unit). Returns (ray_index (H,), range_m (H,), cos_incidence (H,)) for the
    H rays that hit: range along the ray in metres and |n . d| at the hit, in [0, 1].

    The intersector names the first triangle hit; the range is the ray's crossing of that triangle's plane (cheaper
    than asking for hit locations). A ray that grazes its triangle (|n . d| < 1e-9) cannot be ranged that way and
    takes the distance to the triangle's centroid; its contribution, proportional to |n . d|, is nil anyway.
    """
    if len(origins) == 0:
        empty = np.zeros(0)
        return empty.astype(np.int64), empty, empty
    tris, rays = [], []
    # In chunks: trimesh's own intersector builds every (ray, candidate triangle) pair at once, which for a whole
    # view of a detailed mesh is tens of millions of pairs and tens of GB.
    for start in range(0, len(origins), RAY_CHUNK):
        stop = start + RAY_CHUNK
        tri, ray = intersector.intersects_id(origins[start:stop], directions[start:stop], multiple_hits=False,
                                             return_locations=False)
        tris.append(np.asarray(tri, dtype=np.int64))
        rays.append(np.asarray(ray, dtype=np.int64) + start)
    ray, tri = np.concatenate(rays), np.concatenate(tris)
    normals = np.asarray(mesh.face_normals)[tri]
    d = directions[ray]
    to_plane = np.asarray(mesh.triangles_center)[tri] - origins[ray]
    den = np.sum(normals * d, axis=1)
    grazing = np.abs(den) < 1e-9
    rng_m = np.where(grazing, np.linalg.norm(to_plane, axis=1),
                     np.sum(normals * to_plane, axis=1) / np.where(grazing, 1.0, den))
    return ray, np.maximum(rng_m, 0.0), np.clip(np.abs(den), 0.0, 1.0)
