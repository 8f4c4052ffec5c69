"""Space carving (the paper's baseline, and the `fast` preset's initial hull): voxels seen empty are removed.

A zone that detected its first return at range r has seen empty space in every direction of its field of view up to
r; a zone that detected nothing has seen empty space up to the histogram's last bin. A voxel is carved when one view
proves it empty: its bounding sphere lies wholly inside one zone's field of view and wholly nearer than that zone's
first-return onset minus `margin_m`. Everything never proven empty is the hull.

Conservative by construction, for thin parts too: the onset is the first bin whose matched-filtered signal clears
the threshold, which happens at or before the arrival of any surface whose return alone clears it (see `returns`),
and a voxel is carved only if all of it (its bounding sphere) is proven empty. A part too thin for its return to clear
the threshold in any view it faces is what carving can lose: keep the threshold low enough (the default, 5 noise
standard deviations, finds a 16 mm stem at 0.5 m in a 30-degree cone).

Fast: cells are tested coarse to fine (children only of cells still occupied; a child's sphere lies inside its
parent's, so this changes nothing), views in batches, and every test is a matrix product plus a few element-wise
passes over (views, cells) arrays; zones that share a face (the TMF8820's 3x3 grid) share its distances.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.ndimage import distance_transform_edt, gaussian_filter, label, map_coordinates
from skimage.measure import marching_cubes

from spadscan.protocol.errors import CaptureError
from spadscan.protocol.sensor_model import SensorModel

from .bounds import cube_around, scene_bounds
from .returns import DEFAULT_THRESHOLD, check_inputs, detection_filter, first_returns, matched_filter_z, weak_level

DEFAULT_EDGE_DEG = 1.0
"""Carving trusts each zone's field of view only this far (degrees) inside its edges."""
_PAIRS_PER_BATCH = 1 << 22  # cell-view pairs per array pass: ~16 MB float32 arrays
MIN_VIEWS = 3
"""Space that fewer views than this can see is never proven empty by carving, so it is dropped (no data)."""


@dataclass
class CarveResult:
    """The carved hull on a regular grid. Voxel (i, j, k) has its centre at origin + (i, j, k) * voxel_m."""

    occupancy: np.ndarray
    """(R, R, R) bool, True where the space was never proven empty (indices x, y, z)."""
    origin: np.ndarray
    """(3,) centre of voxel (0, 0, 0), metres."""
    voxel_m: np.ndarray
    """(3,) voxel edge lengths, metres."""
    bounds_min: np.ndarray
    """(3,) corner of the grid's box, metres."""
    bounds_max: np.ndarray
    """(3,) opposite corner, metres."""
    threshold: float
    margin_m: float

    def sdf(self) -> np.ndarray:
        """(R, R, R) float32 signed distance to the hull's boundary (metres): negative inside, positive outside.

        From Euclidean distance transforms between voxel centres, so it is exact to about half a voxel.
        """
        occ = self.occupancy
        if not occ.any():
            return np.full(occ.shape, np.inf, np.float32)
        if occ.all():
            return np.full(occ.shape, -np.inf, np.float32)
        out = distance_transform_edt(~occ, sampling=self.voxel_m)
        ins = distance_transform_edt(occ, sampling=self.voxel_m)
        half = 0.5 * float(np.min(self.voxel_m))
        return np.where(occ, -(ins - half), out - half).astype(np.float32)

    def contains(self, points, margin_m: float = 0.0) -> np.ndarray:
        """(n,) bool: points (n, 3) lie inside the hull or within `margin_m` of it (by the SDF, trilinear)."""
        pts = np.asarray(points, dtype=np.float64)
        idx = ((pts - self.origin) / self.voxel_m).T
        sdf = self.sdf().astype(np.float64)
        big = float(np.max(self.voxel_m)) * max(self.occupancy.shape)
        val = map_coordinates(np.nan_to_num(sdf, posinf=big, neginf=-big), idx, order=1, mode="nearest")
        return val <= margin_m

    def mesh(self, smooth_voxels: float = 0.7):
        """The hull as a closed triangle mesh (marching cubes of the occupancy, lightly smoothed), or None if empty."""
        return occupancy_mesh(self.occupancy, self.origin, self.voxel_m, smooth_voxels)


def occupancy_mesh(occupancy: np.ndarray, origin, voxel_m, smooth_voxels: float = 0.7):
    """Marching cubes of a boolean grid at level 0.5 after a Gaussian blur; closed (the grid is padded with empty)."""
    if not occupancy.any():
        return None
    field = np.pad(occupancy.astype(np.float32), 2)
    if smooth_voxels > 0:
        field = gaussian_filter(field, smooth_voxels)
    if field.max() <= 0.5:
        return None
    verts, faces, _, _ = marching_cubes(field, 0.5)
    verts = (verts - 2) * np.asarray(voxel_m) + np.asarray(origin)
    # Increasing field inward: skimage orients faces toward lower values already; keep winding outward.
    mesh = trimesh.Trimesh(verts, faces[:, ::-1], process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _zone_tests(sensor: SensorModel, edge_rad: float) -> list[tuple]:
    """How far (metres) a point lies inside each zone, as sensor-frame unit vectors u for (p - o) . u.

    Per zone: ("cone", axis, sin, cos), the depth being t sin - rho cos with t = (p - o) . axis and rho the distance
    from the axis; or ("rect", x_pair, y_pair), each pair the inward unit normals of two faces through the sensor's
    origin (tan = lo and tan = hi), the depth the smallest of the four distances inside them. Zones are shrunk by
    `edge_rad` on every side. The TMF8820's nine zones share three x and three y face pairs, so the normals are
    tuples: a caller computes each distinct one once.
    """
    tests = []
    for zone in sensor.zones:
        if zone.kind == "cone":
            half = max(zone.half_angle_rad - edge_rad, 0.0)
            tests.append(("cone", tuple(np.asarray(zone.axis, float)), np.sin(half), np.cos(half)))
            continue
        pairs = []
        for axis, (lo, hi) in ((0, zone.tan_x), (1, zone.tan_y)):
            lo, hi = np.tan(np.arctan(lo) + edge_rad), np.tan(np.arctan(hi) - edge_rad)
            if lo > hi:
                lo = hi = 0.5 * (lo + hi)
            pair = []
            for sign, t in ((1.0, lo), (-1.0, hi)):  # inside: x/z >= lo, x/z <= hi (or y)
                normal = np.zeros(3)
                normal[axis], normal[2] = sign, -sign * t
                pair.append(tuple(normal / np.linalg.norm(normal)))
            pairs.append(tuple(pair))
        tests.append(("rect", pairs[0], pairs[1]))
    return tests


DROP, KEEP, SPLIT = 0, 1, 2


def _classify_cells(centres: np.ndarray, radius: float, poses: np.ndarray, sensor: SensorModel,
                    limit: np.ndarray, final: bool, min_views: int, edge_rad: float,
                    keep_returns_m: float = 0.0) -> np.ndarray:
    """(M,) int8 verdicts on cells (centres (M, 3) metres, bounding-sphere radius): DROP, KEEP or SPLIT.

    DROP: some view proves the whole cell empty, or fewer than `min_views` views can see any of it (space nobody
    scanned, such as the box's corners beside a sensor) and no view that sees it has its first return there (some
    of the cell within `keep_returns_m` beyond the range the view proved empty). KEEP: no view can carve any part of
    it and at least `min_views` views see all of it, so every voxel inside it is kept (interiors are not tested again
    at finer levels). SPLIT: undecided, test its children. A `final` voxel is never split: it is kept unless carved,
    and it is seen by a view when its centre is. limit (n, zones): range (metres) in front of which each zone saw
    nothing.
    """
    tests = _zone_tests(sensor, edge_rad)
    n, m = len(poses), len(centres)
    # float32 coordinates relative to the cells' mean: sub-micron rounding for any rig far from its base.
    ref = centres.mean(axis=0) if m else np.zeros(3)
    origins = poses[:, :3, 3] - ref
    units = {u for test in tests for u in ((test[1],) if test[0] == "cone" else test[1] + test[2])}
    # (p - o) . u for a sensor-frame unit vector u is [p, 1] . [R u, -o . R u]: one matrix product per batch. So is
    # |p - o|^2 - |p|^2 = [p, 1] . [-2 o, |o|^2]. Arrays are (views, cells): with the cells along rows, the
    # per-view ranges broadcast down columns, several times faster than along short rows.
    forms = {}
    for u in units:
        w = poses[:, :3, :3] @ np.asarray(u)  # (n, 3) world
        forms[u] = np.concatenate([w, -np.einsum("ni,ni->n", w, origins)[:, None]], axis=1).astype(np.float32)
    to_origin = np.concatenate([-2 * origins, np.einsum("ni,ni->n", origins, origins)[:, None]],
                               axis=1).astype(np.float32)
    cells = (centres - ref).astype(np.float32)
    lim_all = limit.astype(np.float32)
    carved = np.zeros(m, bool)
    at_return = np.zeros(m, bool)  # some view that sees the cell has its first return there
    partly = np.zeros(m, bool)  # some view could carve part of the cell
    touched = np.zeros(m, np.int32)  # views that see some of the cell (final voxels: its centre)
    whole = np.zeros(m, np.int32)  # views that see all of it
    alive = np.arange(m)
    order = np.random.default_rng(0).permutation(n)  # spread early batches over the sphere: they carve the most
    r = np.float32(radius)
    seen_depth = np.float32(0.0 if final else -radius)
    start = 0
    while start < n and alive.size:
        batch = order[start: start + max(1, _PAIRS_PER_BATCH // max(alive.size, 1))]
        start += len(batch)
        p = np.ones((4, alive.size), np.float32)
        p[:3] = cells[alive].T

        def along(form):  # (n, 4) per view -> (views, cells): [p, 1] . form
            # einsum, not a BLAS product: this one is as fast on one core, and BLAS threads that wait spinning
            # after a product slow every pass after it when another process shares the cores (2.5x the time).
            return np.einsum("vc,cm->vm", form[batch], p)

        d2 = along(to_origin) + np.einsum("im,im->m", p[:3], p[:3])[None]  # (views, cells)
        d = np.sqrt(np.maximum(d2, 0))
        far, near = d + r, d - r  # the cell's farthest and nearest range from the sensor
        cut = np.zeros(d.shape, bool)
        held = np.zeros(d.shape, bool)
        part = np.zeros(d.shape, bool)
        sees = np.zeros(d.shape, np.uint8)  # zones that see it: a few, never over 255
        sees_all = np.zeros(d.shape, np.uint8)
        pairs: dict[tuple, np.ndarray] = {}  # rect zones' face pairs: distance inside both faces
        for z, test in enumerate(tests):
            lim = lim_all[batch, z][:, None]
            if test[0] == "cone":
                t = along(forms[test[1]])
                rho = np.sqrt(np.maximum(d2 - t * t, 0))
                depth = t * np.float32(test[2]) - rho * np.float32(test[3])  # distance inside the cone's surface
            else:
                for pair in test[1:]:
                    if pair not in pairs:
                        pairs[pair] = np.minimum(along(forms[pair[0]]), along(forms[pair[1]]))
                depth = np.minimum(pairs[test[1]], pairs[test[2]])
            # A zone whose histogram holds no data (limit -inf: a dropped frame) looked at nothing: it neither
            # carves nor counts towards min_views.
            looked = lim > np.float32(-np.inf)
            inside = depth >= r
            cut |= inside & (far <= lim)
            seen = (depth >= seen_depth) & looked
            sees += seen
            if keep_returns_m > 0:
                held |= seen & (far > lim) & (near <= lim + np.float32(keep_returns_m))
            if not final:
                part |= (depth > -r) & (near < lim)
                sees_all += inside & looked
        touched[alive] += sees.sum(axis=0, dtype=np.int32)
        gone = cut.any(axis=0)
        carved[alive[gone]] = True
        at_return[alive] |= held.any(axis=0)
        if not final:
            partly[alive] |= part.any(axis=0)
            whole[alive] += sees_all.sum(axis=0, dtype=np.int32)
        alive = alive[~gone]
    verdict = np.full(m, SPLIT, np.int8)
    if final:
        verdict[:] = KEEP
    else:
        verdict[~partly & (whole >= min_views)] = KEEP
    verdict[carved | ((touched < min_views) & ~at_return)] = DROP
    return verdict


def main_components(occupancy: np.ndarray, min_fraction: float) -> np.ndarray:
    """The occupancy without connected pieces smaller than `min_fraction` of the largest (specks left at the box's
    walls and beside sensors, where few views looked)."""
    lab, n = label(occupancy)
    if n <= 1:
        return occupancy.copy()
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    keep = sizes >= min_fraction * sizes.max()
    keep[0] = False
    return keep[lab]


def _paint(occ: np.ndarray, cells: np.ndarray, factor: int) -> None:
    """Mark every final voxel inside the given cells (indices at a level `factor` times coarser) occupied."""
    if not len(cells):
        return
    sub = np.stack(np.meshgrid(*[np.arange(factor)] * 3, indexing="ij"), -1).reshape(-1, 3)
    for start in range(0, len(cells), max(1, (1 << 22) // len(sub))):
        idx = (factor * cells[start: start + (1 << 22) // len(sub) or 1][:, None, :] + sub[None]).reshape(-1, 3)
        occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True


def carve_limits(hists, sensor: SensorModel, threshold: float, margin_m: float,
                 filter: str = "leading", weak_threshold: float | None = None) -> np.ndarray:
    """(n, zones) range (metres) up to which each view's zone saw empty space, less the margin.

    The onset is where the filtered signal first clears `threshold`. A higher threshold moves the onset up the
    leading edge of a strong return (a tighter hull), but must not carve away a weak return in front of it (a thin
    part, a surface at the edge of the field of view): when the signal clears the default threshold earlier and
    drops below it again before the strong return, that weak return's onset is kept; a zone that saw nothing above
    the default threshold is carved to the end of its histogram. `weak_threshold` (noise standard deviations, None:
    the default threshold) sets that weak level instead, capped at `threshold`.
    """
    lag = detection_filter(sensor, filter)[2]
    z = matched_filter_z(np.asarray(hists, dtype=np.float64), sensor, filter)
    weak = z > weak_level(threshold, weak_threshold)
    strong = z > threshold
    has_weak, has_strong = weak.any(axis=-1), strong.any(axis=-1)
    w = np.argmax(weak, axis=-1)
    s = np.where(has_strong, np.argmax(strong, axis=-1), z.shape[-1])
    # End of the run above the weak level that starts at w: the first bin at or after w that is not above it.
    bins = np.arange(z.shape[-1])
    after = ~weak & (bins >= w[..., None])
    run_end = np.where(after.any(axis=-1), np.argmax(after, axis=-1), z.shape[-1])
    onset = np.where(has_strong & (s < run_end), s, w).astype(np.float64) - lag
    rng = sensor.range_of_bin(onset)
    return np.where(has_weak, rng, sensor.max_range_m) - margin_m


def carve_hull(hists, poses, sensor: SensorModel, *, bounds_min, bounds_max, resolution: int,
               threshold: float = DEFAULT_THRESHOLD, margin_m: float | None = None,
               floor_z: float | None = None, min_views: int = MIN_VIEWS, edge_deg: float = DEFAULT_EDGE_DEG,
               filter: str = "leading", keep_returns_m: float = 0.0,
               weak_threshold: float | None = None, usable: np.ndarray | None = None) -> CarveResult:
    """Space-carve the box [bounds_min, bounds_max] (metres) on a resolution^3 grid.

    hists (n, zones, bins) counts; poses (n, 4, 4) sensor-to-world (metres, +z boresight). threshold: detection
    threshold in standard deviations of the matched-filtered background noise. margin_m: extra range left uncarved
    in front of every first return (default: one bin width, at least 2 mm). floor_z: when given, space below this
    height is empty (the scene stands on a floor that the histograms do not show). min_views: space in the field of
    view of fewer views than this (corners of the box, beside a sensor) is taken to be empty: it was not scanned.
    keep_returns_m: ...except where a view that sees it has its first return there: space up to this far (metres)
    beyond the range a zone proved empty is kept however few views see it (0: the min_views rule alone). The top of a
    tall object, far from the point the views aim at, lies in few views' fields of view, and the rule would cut it
    off while those views' returns land on it. weak_threshold: a run of bins above this level that ends before the
    signal clears `threshold` stops carving there (see `carve_limits`; None: the default threshold). usable (n, zones)
    bool, or None for all: a histogram marked False (one no sensor could have produced: all zero, saturated) proves
    nothing empty, where read as "no return" it would clear its zone's whole field of view.
    """
    h, p = check_inputs(hists, poses, sensor)
    lo, hi = np.asarray(bounds_min, float), np.asarray(bounds_max, float)
    if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise CaptureError(f"bounds must be two finite 3-vectors (metres), got {lo.tolist()} and {hi.tolist()}")
    if np.any(hi <= lo):
        raise CaptureError(f"bounds_max {hi.tolist()} must exceed bounds_min {lo.tolist()} on every axis (metres)")
    if not (isinstance(resolution, (int, np.integer)) and 2 <= resolution <= 1024):
        raise CaptureError(f"resolution {resolution} must be an integer in [2, 1024]")
    if not (np.isfinite(threshold) and threshold > 0):
        raise CaptureError(f"detection threshold {threshold} must be > 0 (standard deviations of the noise)")
    if not (isinstance(min_views, (int, np.integer)) and min_views >= 0):
        raise CaptureError(f"min_views {min_views} must be an integer >= 0")
    if margin_m is None:
        margin_m = max(sensor.bin_width_m, 0.002)
    if not (np.isfinite(edge_deg) and 0 <= edge_deg < 45):
        raise CaptureError(f"edge {edge_deg} degrees must lie in [0, 45)")
    edge_rad = float(np.radians(edge_deg))
    if not (np.isfinite(margin_m) and margin_m >= 0):
        raise CaptureError(f"margin {margin_m} m must be finite and >= 0")
    if not (np.isfinite(keep_returns_m) and keep_returns_m >= 0):
        raise CaptureError(f"keep_returns_m {keep_returns_m} must be finite and >= 0 metres")
    if weak_threshold is not None and not (np.isfinite(weak_threshold) and weak_threshold > 0):
        raise CaptureError(f"weak detection threshold {weak_threshold} must be > 0 (standard deviations of the noise)")
    limit = carve_limits(h, sensor, threshold, margin_m, filter, weak_threshold)
    if usable is not None:
        limit = np.where(np.asarray(usable, bool), limit, -np.inf)
    voxel = (hi - lo) / resolution
    # Levels: resolution / 2^k, ..., resolution, starting no coarser than 8 cells per side.
    levels = [int(resolution)]
    while levels[0] % 2 == 0 and levels[0] // 2 >= 8:
        levels.insert(0, levels[0] // 2)
    occ = np.zeros((resolution,) * 3, bool)
    cells = np.stack(np.meshgrid(*[np.arange(levels[0])] * 3, indexing="ij"), -1).reshape(-1, 3)
    octants = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(-1, 3)
    for li, res in enumerate(levels):
        final = li + 1 == len(levels)
        size = (hi - lo) / res
        centres = lo + (cells + 0.5) * size
        verdict = _classify_cells(centres, 0.5 * float(np.linalg.norm(size)), p, sensor, limit, final, min_views,
                                  edge_rad, keep_returns_m)
        if floor_z is not None:
            # Below the floor: empty. Final voxels go by their centres; a coarse cell across the floor is split.
            if final:
                verdict[centres[:, 2] < floor_z] = DROP
            else:
                verdict[centres[:, 2] + 0.5 * size[2] < floor_z] = DROP
                verdict[(verdict == KEEP) & (centres[:, 2] - 0.5 * size[2] < floor_z)] = SPLIT
        _paint(occ, cells[verdict == KEEP], resolution // res)
        if not final:
            cells = (2 * cells[verdict == SPLIT][:, None, :] + octants[None]).reshape(-1, 3)
    return CarveResult(occ, lo + 0.5 * voxel, voxel, lo, hi, float(threshold), float(margin_m))


def carve_scene(hists, poses, sensor: SensorModel, *, resolution: int = 128, threshold: float = DEFAULT_THRESHOLD,
                margin_m: float | None = None, floor_z: float | None = None, bounds=None,
                edge_deg: float = DEFAULT_EDGE_DEG, coarse: int = 48, keep_returns_m: float = 0.0,
                weak_threshold: float | None = None, usable: np.ndarray | None = None,
                min_views: int = MIN_VIEWS) -> CarveResult:
    """Space carving without knowing the scene's box: carve coarsely inside the first returns' footprints (or
    `bounds`, a pair of (3,) corners in metres), then again at `resolution` in a cube around what is left
    (`usable`, `min_views`: see `carve_hull`)."""
    h, p = check_inputs(hists, poses, sensor)
    if bounds is None:
        lo, hi = scene_bounds(first_returns(h, sensor, threshold, "matched"), p, sensor, floor_z=floor_z)
    else:
        lo, hi = (np.asarray(b, float) for b in bounds)
    lo, hi = cube_around(lo, hi)
    kw = dict(threshold=threshold, margin_m=margin_m, floor_z=floor_z, edge_deg=edge_deg,
              keep_returns_m=keep_returns_m, weak_threshold=weak_threshold, usable=usable, min_views=min_views)
    first = carve_hull(h, p, sensor, bounds_min=lo, bounds_max=hi, resolution=min(coarse, resolution), **kw)
    if not first.occupancy.any():
        return first
    idx = np.argwhere(main_components(first.occupancy, 0.05))
    tight_lo = first.origin + (idx.min(axis=0) - 1.5) * first.voxel_m
    tight_hi = first.origin + (idx.max(axis=0) + 1.5) * first.voxel_m
    lo, hi = cube_around(np.maximum(tight_lo, lo), np.minimum(tight_hi, hi))
    return carve_hull(h, p, sensor, bounds_min=lo, bounds_max=hi, resolution=resolution, **kw)
