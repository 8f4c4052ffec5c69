"""Returns the mesh does not account for: first returns measured where the mesh has no surface.

A zone's first return at range r says that something stands in the zone's field of view about r from the sensor. The
mesh accounts for it when some of its surface, or the table's, lies in that field of view no farther than r plus
LOST_TOLERANCE_M: nearer surface would have returned first, and the first return of a surface a little beyond the
nearest point of the mesh is the bulk of the mesh behind that point. A part of the object lost whole (a thin rod that
carving cut away, a limb the fit let go) leaves the returns it gave unaccounted for, and nothing else tells: a mesh
of next to nothing is one piece, seen by many views, and the fit's misfit is small where a thin part's photons are
few. Only returns that can have come from the scene's sphere are judged: beyond it lies the room, which no fit
models. A weak return at the range of a return of another zone of its view that the mesh accounts for is that one's
light in the wrong zone (LEAK_SHARE), and is accounted for with it.

Only each zone's nearest return is judged, so a lost part is found only where some zone saw it before anything else:
a part that stands out of the object (a rod, a set of legs, a limb, a top). A part lost behind or beside surface
the mesh keeps in the same zones (a mug's handle, a lamp's stem under its shade, one leg of four) leaves returns that
the kept surface accounts for. Surface the mesh has where nothing returned (a phantom lump) is not judged here: the
misfit check sees it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from spadscan.protocol.sensor_model import SensorModel, zone_masks

from .carving.bounds import zone_axis, zone_edges, zone_top_z
from .carving.returns import DEFAULT_THRESHOLD, first_returns
from .carving.view_subset import MAX_SETUP_VIEWS, spread_views

LOST_TOLERANCE_M = 0.03
"""Range (metres) by which a first return may lie nearer than the mesh's nearest surface in its zone and still be
accounted for: the matched filter's arrival errs by a bin or two, a real sensor's range by more (docs/end_of_run.md
gives the measurements)."""
LOST_SHARE_SIMULATED = 0.07
"""Share of the judged first returns of a simulated capture unaccounted for above which the result says so: twice
the largest share a good mesh leaves (3.5 %: the true pawn on a bright 9-zone capture; every good fit of a one-zone
capture 0; docs/end_of_run.md)."""
LOST_SHARE_MEASURED = 0.15
"""The same for a measured capture: twice what good fits of the public dataset's real pyramid leave (7.7 %)."""
LEAK_SHARE = 0.02
"""A return whose peak z-score (matched filter, noise standard deviations) is at most this share of that of a return
of another zone of the same view, at its range (within LOST_TOLERANCE_M), is that return's light in the wrong zone:
a 9-zone sensor's crosstalk puts a share of every zone's signal into the others, and the unmixing that carving's
returns start with leaves a residue that clears the threshold beside a bright surface. With the mesh accounting for
the bright return, it accounts for the weak one (docs/end_of_run.md: 1-15 % of a good 9-zone capture's returns
before, under 4 % after). A z-score, not a photon count: of a bright return it grows as the square root of its
photons, so the share of signal is far under 2 %; the value is what the captures measured."""
LOST_MIN = 3
"""Fewest returns unaccounted for that make a pattern: one view's noise can clear the threshold anywhere."""
MESH_POINTS = 10_000
"""Points drawn over the mesh's surface, and vertices of it at most, that each view's zones are tested on."""


@dataclass
class LostReturns:
    """First returns, at carving's default threshold, that the mesh does not account for."""

    returns: int
    """Returns judged: detected in a usable histogram, at a range where the zone's field of view meets the scene's
    sphere."""
    lost: int
    """Of them, those with no surface of the mesh or the table in their zone's field of view nearer than their range
    plus `tolerance_m`."""
    limit: float = LOST_SHARE_SIMULATED
    """Share of lost returns above which the result says so: `limit_for` the capture."""
    tolerance_m: float = LOST_TOLERANCE_M
    heights_m: tuple[float, float] | None = None
    """10th and 90th percentile of the height (world z, metres) of the lost returns, each taken on its zone's axis at
    its range; None when none was lost."""

    @property
    def share(self) -> float:
        """Share of the judged returns lost (0 when none was judged)."""
        return self.lost / self.returns if self.returns else 0.0

    @property
    def says(self) -> bool:
        """Whether enough returns are lost for the result to say so (`limit`, and at least LOST_MIN of them)."""
        return self.lost >= LOST_MIN and self.share > self.limit

    def to_dict(self) -> dict:
        return {"returns": self.returns, "lost": self.lost, "share": self.share, "tolerance_m": self.tolerance_m,
                "heights_m": None if self.heights_m is None else list(self.heights_m), "limit": self.limit}


def limit_for(measured: bool) -> float:
    """The share of lost returns above which a result says so: LOST_SHARE_MEASURED or LOST_SHARE_SIMULATED."""
    return LOST_SHARE_MEASURED if measured else LOST_SHARE_SIMULATED


def nearest_surface(points: np.ndarray, poses: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """(V, Z) range (metres) from each view's sensor to the nearest of `points` (n, 3, world metres) in each zone's
    field of view; inf where none lies in it. poses (V, 4, 4) sensor to world."""
    near = np.full((len(poses), len(sensor.zones)), np.inf)
    for v, pose in enumerate(poses):
        rel = (points - pose[:3, 3]) @ pose[:3, :3]
        dist = np.linalg.norm(rel, axis=1)
        for z, held in enumerate(zone_masks(sensor.zones, rel)):
            if held.any():
                near[v, z] = float(dist[held].min())
    return near


def table_range(normal: np.ndarray, offset: float, poses: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """(V, Z) range (metres) from each view's sensor to the nearest point of the plane normal . x = offset (normal
    unit, pointing up into the free side) in each zone's field of view; inf where the zone does not look at it or
    the sensor stands under the plane. The nearest point lies along the zone's direction that heads most steeply
    down onto the plane (`zone_top_z` of the rotations turned so that their z is the plane's down): exact for a cone,
    for a rect zone its edges', or straight down where that lies in the zone."""
    normal = np.asarray(normal, np.float64)
    height = poses[:, :3, 3] @ normal - offset  # (V,): the sensor's height above the plane
    turned = np.array(poses[:, :3, :3], np.float64)
    turned[:, 2, :] = (-normal) @ poses[:, :3, :3]  # row 2: each sensor-frame direction's component down the normal
    out = np.full((len(poses), len(sensor.zones)), np.inf)
    for z, zone in enumerate(sensor.zones):
        steepest = zone_top_z(zone, turned)
        if zone.kind == "rect":
            steepest = np.where(np.asarray(zone.holds(turned[:, 2, :]), bool), 1.0, steepest)
        with np.errstate(divide="ignore", invalid="ignore"):
            out[:, z] = np.where((steepest > 0) & (height > 0), height / steepest, np.inf)
    return out


def in_sphere_reach(ranges: np.ndarray, poses: np.ndarray, sensor: SensorModel, center: np.ndarray,
                    radius: float) -> np.ndarray:
    """(V, Z) bool: whether a return at `ranges` (V, Z metres, NaN for none) can have come from inside the sphere
    (`center` (3,), `radius` metres): the sphere of that range around the sensor meets the ball within the zone's
    field of view (the zone taken as the cone around its axis that holds its edges)."""
    eye = poses[:, :3, 3]
    to_c = np.asarray(center, np.float64) - eye
    dist = np.linalg.norm(to_c, axis=1)  # (V,)
    out = np.zeros(ranges.shape, bool)
    for z, zone in enumerate(sensor.zones):
        axis = zone_axis(zone)
        half = float(np.arccos(np.clip(zone_edges(zone, 16) @ axis, -1.0, 1.0)).max())
        world_axis = poses[:, :3, :3] @ axis
        off_axis = np.arccos(np.clip(np.einsum("vi,vi->v", world_axis, to_c) / np.maximum(dist, 1e-12), -1, 1))
        r = ranges[:, z]
        with np.errstate(invalid="ignore", divide="ignore"):
            # The points at range r inside the ball lie within this angle of the direction to its centre.
            cos_cap = (r * r + dist * dist - radius * radius) / (2.0 * r * dist)
            cap = np.arccos(np.clip(cos_cap, -1.0, 1.0))
            out[:, z] = np.isfinite(r) & (np.abs(r - dist) <= radius) & (off_axis - half <= cap)
    return out


def lost_returns(hists: np.ndarray, poses: np.ndarray, sensor: SensorModel, mesh, center, radius: float,
                 table: tuple[np.ndarray, float] | None = None, usable: np.ndarray | None = None,
                 measured: bool = False, max_views: int = MAX_SETUP_VIEWS) -> LostReturns:
    """The first returns of `hists` (V, zones, bins, frames summed as carving reads them; poses (V, 4, 4) sensor to
    world, metres) that `mesh` (a trimesh.Trimesh, world metres) and the `table` plane (normal (3,), offset metres),
    if any, do not account for. `center`, `radius`: the scene's sphere (metres). usable (V, zones) bool, None for
    all: histograms that hold data. `measured`: a real capture (`limit_for`). Of a capture of more than `max_views`
    views with data, that many spread evenly over it are judged (the share is what matters)."""
    hists, poses = np.asarray(hists, np.float64), np.asarray(poses, np.float64)
    keep = spread_views(poses, max_views, usable)
    hists, poses = hists[keep], poses[keep]
    usable = None if usable is None else np.asarray(usable, bool)[keep]
    returns = first_returns(hists, sensor, DEFAULT_THRESHOLD, "matched", usable=usable)  # none where unusable
    rng = np.where(returns.detected, returns.arrival_range_m(sensor), np.nan)
    judged = in_sphere_reach(rng, poses, sensor, center, radius)
    if not judged.any():
        return LostReturns(0, 0, limit_for(measured))
    near = nearest_surface(_surface_points(mesh), poses, sensor)
    if table is not None:
        near = np.minimum(near, table_range(table[0], table[1], poses, sensor))
    lost = judged & ~(near <= np.where(judged, rng, 0.0) + LOST_TOLERANCE_M)
    lost &= ~leaked(lost, judged & ~lost, rng, returns.peak_z)
    heights = None
    if lost.any():
        v, z = np.nonzero(lost)
        axes = np.stack([zone_axis(sensor.zones[k]) for k in z])
        z_world = poses[v, 2, 3] + rng[v, z] * np.einsum("ni,ni->n", poses[v, 2, :3], axes)
        heights = (float(np.percentile(z_world, 10)), float(np.percentile(z_world, 90)))
    return LostReturns(int(judged.sum()), int(lost.sum()), limit_for(measured), LOST_TOLERANCE_M, heights)


def leaked(lost: np.ndarray, kept: np.ndarray, ranges: np.ndarray, peak_z: np.ndarray) -> np.ndarray:
    """(V, Z) bool: the `lost` returns that are light of a `kept` return (one the mesh accounts for) of another zone
    of the same view in the wrong zone: at its range (within LOST_TOLERANCE_M; `ranges` (V, Z) metres) and at most
    LEAK_SHARE of its peak z-score (`peak_z` (V, Z), noise standard deviations of the matched filter)."""
    near = np.abs(ranges[:, :, None] - ranges[:, None, :]) <= LOST_TOLERANCE_M  # (V, lost zone, source zone)
    weak = peak_z[:, :, None] <= LEAK_SHARE * peak_z[:, None, :]
    return lost & (near & weak & kept[:, None, :]).any(axis=2)


def _surface_points(mesh) -> np.ndarray:
    """(n, 3) points of the mesh's surface: MESH_POINTS drawn over its area (seeded: the same mesh, the same points)
    and as many of its vertices, taken evenly, so that a part too small for the draw to land on keeps its corners;
    (0, 3) for a mesh without surface."""
    verts = np.asarray(mesh.vertices, np.float64).reshape(-1, 3)
    if len(mesh.faces) == 0 or not mesh.area > 0:
        return np.zeros((0, 3))
    step = max(1, -(-len(verts) // MESH_POINTS))
    drawn = trimesh.sample.sample_surface(mesh, MESH_POINTS, seed=0)[0]
    return np.vstack([np.asarray(drawn, np.float64), verts[::step]])


__all__ = ["LostReturns", "lost_returns", "nearest_surface", "table_range", "in_sphere_reach", "limit_for", "leaked",
           "LEAK_SHARE", "LOST_TOLERANCE_M", "LOST_SHARE_SIMULATED", "LOST_SHARE_MEASURED", "LOST_MIN", "MESH_POINTS"]
