"""Mesh quality metrics by the project's convention (docs/metrics.md), numpy + trimesh + a KD-tree, no torch.

Both meshes are sampled uniformly by area (`n_points` each, from a fixed seed); distances are between those samples:

- accuracy     = mean distance from each reconstruction sample to the nearest ground-truth sample (mm),
- completeness = mean distance from each ground-truth sample to the nearest reconstruction sample (mm),
- Chamfer      = (accuracy + completeness) / 2 (mm),
- F-score      = harmonic mean of precision (share of reconstruction samples within the threshold of the ground truth)
                 and recall (share of ground-truth samples within the threshold of the reconstruction),
- normal error = mean angle between each sample's face normal and the normal at its nearest sample on the other
                 mesh, using |<n, n~>| so that flipped orientation does not count (degrees), averaged both ways.

Sample-to-sample distances have a floor: two identical meshes score about 0.5 sqrt(area / n_points) (~0.35 mm on
the bunny at 300,000 points), below which differences cannot be resolved. scipy's cKDTree answers 300,000 nearest
neighbour queries in well under a second when the surfaces are close, where trimesh's exact closest-point search
takes about 30 s; for samples far from the other surface `nearest_samples` uses patch bounds instead (still exact).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

from spadscan.protocol.errors import MeshError

from .nearest import SampleIndex, nearest_samples

MAX_POINTS = 20_000_000
UNBUDGETED_S = 120.0
"""Seconds a run without a time budget (`spadscan reconstruct --steps N`) measures the metrics' distances for, at
most (`spadscan eval`'s default --budget-s): meshes that lie far apart measure slowly (a 0.1 m sphere against a
ground truth 1 m across: 105 s at 300,000 points, and minutes more at 2.5 m, a ground truth in the wrong unit),
and a run stopped on its step count must end all the same. (The per-vertex normal error, measured before them, is
not bounded: its time grows with the mesh's vertices alone, about 1 ms each where the meshes lie far apart.)"""
FIRST_QUERIES = 500
"""Samples per mesh whose distances are measured before a deadline is looked at: the fewest that metrics stopped
by one rest on (an unbiased share of the samples, each measured against all of the other mesh's). Later chunks
double. Few, because a query can be slow whatever is done: one at the centre of a sphere sits at nearly the same
distance from every sample of it (a ground truth a tenth the size of the mesh, 10-15 ms a query), and 5,000 of them
overran a 20 s budget by minutes."""


@dataclass(frozen=True)
class MeshMetrics:
    """Errors of a reconstruction against ground truth. Millimetres and degrees (the user's units)."""

    chamfer_mm: float
    """(accuracy + completeness) / 2."""
    accuracy_mm: float
    """Mean distance reconstruction -> ground truth."""
    completeness_mm: float
    """Mean distance ground truth -> reconstruction."""
    fscore_5mm: float
    """F-score in [0, 1] at `fscore_threshold_mm` (5 mm unless asked otherwise)."""
    precision: float
    """Share of reconstruction samples within the threshold of the ground truth."""
    recall: float
    """Share of ground-truth samples within the threshold of the reconstruction."""
    normal_error_deg: float
    """Mean unsigned normal angle error, both directions averaged."""
    fscore_threshold_mm: float
    n_points: int
    """Samples per mesh: the density each side's nearest distances are measured against."""
    seed: int
    queries: int
    """Samples per mesh whose nearest distance was measured: `n_points` unless a deadline stopped the metrics early
    (the first samples drawn, themselves uniform by area, so the figures are a coarser estimate, not a biased one)."""

    def to_dict(self) -> dict:
        """The fields as a dict; the F-score's key names its threshold (`fscore_5mm`, or e.g. `fscore_10mm`), so that
        a script reading `fscore_5mm` never gets an F-score at another threshold."""
        d = asdict(self)
        if self.fscore_threshold_mm != 5.0:
            d[f"fscore_{self.fscore_threshold_mm:g}mm"] = d.pop("fscore_5mm")
        return d


def check_mesh(mesh, what: str) -> None:
    """Refuse meshes that cannot be sampled: no triangles, non-finite vertices, zero area."""
    import trimesh

    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"{what}: expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise MeshError(f"{what}: has no triangles")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f"{what}: has non-finite vertex coordinates")
    if not mesh.area > 0:
        raise MeshError(f"{what}: has zero surface area")


def sample_surface(mesh, n_points: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Sample points uniformly by area. Returns points (n, 3) metres and their faces' unit normals (n, 3)."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)  # (F, 3, 3)
    edge1, edge2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    cross = np.cross(edge1, edge2)
    double_area = np.linalg.norm(cross, axis=1)
    cdf = np.cumsum(double_area)
    face = np.searchsorted(cdf, rng.random(n_points) * cdf[-1], side="right")
    face = np.minimum(face, len(tri) - 1)  # guards the rounding case u * total == total
    u, v = rng.random(n_points), rng.random(n_points)
    flip = u + v > 1  # reflect the unit square's upper half back into the triangle
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    points = tri[face, 0] + u[:, None] * edge1[face] + v[:, None] * edge2[face]
    return points, cross[face] / double_area[face, None]  # sampled faces have area > 0 by construction


SIZE_RATIO = 5.0
"""Meshes whose bounding-box diagonals differ by more than this factor are not one object in one unit (`mismatch`).
A unit mistake differs 10x (cm taken for mm) or more (100x: cm read as metres); 188 reconstructions scored against
their own scene's ground truth, failed ones with stray blobs included, stayed within 3.5x."""


def mismatch(mesh, gt, compare_sizes: bool = True) -> str | None:
    """One line when a reconstruction `mesh` and its ground truth `gt` (trimesh meshes, metres) plainly are not one
    object in one frame and unit: their bounding boxes do not overlap, or, with `compare_sizes`, their diagonals
    differ over SIZE_RATIO times; else None. A Chamfer of hundreds of mm says that something is wrong, not what."""
    a, b = np.asarray(mesh.bounds, float), np.asarray(gt.bounds, float)
    said = []
    if np.any(a[0] > b[1]) or np.any(b[0] > a[1]):
        said.append(f"the bounding boxes of the reconstruction and the ground truth do not overlap "
                    f"({_bounds(a)} and {_bounds(b)} m)")
    sizes = {"the reconstruction": float(np.linalg.norm(a[1] - a[0])),
             "the ground truth": float(np.linalg.norm(b[1] - b[0]))}
    large, small = sorted(sizes, key=sizes.get, reverse=True)
    if compare_sizes and sizes[small] > 0 and sizes[large] / sizes[small] > SIZE_RATIO:
        said.append(f"{large} is {sizes[large] / sizes[small]:.3g}x the size of {small} (bounding-box diagonals "
                    f"{sizes[large]:.3g} and {sizes[small]:.3g} m)")
    return "; ".join(said) if said else None


def _bounds(bounds) -> str:
    # Millimetres are enough to see two boxes apart; + 0.0 turns a rounded -0.0 into 0.
    return " .. ".join("[" + ", ".join(f"{round(v, 3) + 0.0:g}" for v in corner) + "]" for corner in bounds)


def vertex_normal_error_deg(mesh, gt, n_gt: int = 300_000, seed: int = 0) -> np.ndarray:
    """Per-vertex angle (degrees) between the mesh's vertex normal and the face normal of the ground truth at the
    nearest of n_gt area-uniform ground-truth samples, using |<n, n~>| (orientation-free, as in the paper).
    (n_vertices,).

    The ground truth's face normals, not its vertex normals interpolated across faces: a CAD or built-in ground
    truth shares its vertices between faces that meet at a sharp edge, so its vertex normals average those faces
    and would tilt the "true" normal across every flat face (a perfect mesh of a pyramid scored ~40 deg)."""
    check_mesh(mesh, "reconstruction")
    check_mesh(gt, "ground truth")
    g_pts, g_nrm = sample_surface(gt, int(n_gt), np.random.default_rng(seed))
    _, idx = nearest_samples(np.asarray(mesh.vertices, dtype=np.float64), g_pts,
                             spacing_m=math.sqrt(gt.area / n_gt))
    vn = np.asarray(mesh.vertex_normals, dtype=np.float64)
    cos = np.clip(np.abs(np.einsum("ij,ij->i", vn, g_nrm[idx])), 0.0, 1.0)
    return np.degrees(np.arccos(cos))


def mesh_metrics(pred, gt, *, n_points: int = 300_000, seed: int = 0, fscore_threshold_m: float = 0.005,
                 deadline: float | None = None, clock: Callable[[], float] = time.perf_counter) -> MeshMetrics:
    """Compare a reconstruction `pred` with ground truth `gt` (both trimesh.Trimesh in metres).

    With a `deadline` (a `clock()` reading), the samples' distances are measured in chunks, and no chunk is begun
    that the last one's pace says would end after it: a time budget's run ends on time however far the meshes lie
    apart (their metrics' time grows faster than the points, by a factor no probe foretells well). At least
    FIRST_QUERIES samples per mesh are measured; `queries` says how many were."""
    check_mesh(pred, "reconstruction")
    check_mesh(gt, "ground truth")
    if not (isinstance(n_points, (int, np.integer)) and 1 <= n_points <= MAX_POINTS):
        raise MeshError(f"points {n_points} must be an integer in [1, {MAX_POINTS}]")
    if not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise MeshError(f"seed {seed} must be an integer >= 0")
    if not (math.isfinite(fscore_threshold_m) and 0 < fscore_threshold_m < 10):
        raise MeshError(f"F-score threshold {fscore_threshold_m} m must be in (0, 10) m")
    if deadline is not None and math.isnan(deadline):
        raise MeshError("the metrics' deadline is NaN (a clock reading, or None for none)")
    # Two independent streams from one seed: identical meshes then show the sampling floor, not a false zero.
    rng_pred, rng_gt = (np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(2))
    p_pts, p_nrm = sample_surface(pred, int(n_points), rng_pred)
    g_pts, g_nrm = sample_surface(gt, int(n_points), rng_gt)
    to_gt = SampleIndex(g_pts, spacing_m=math.sqrt(gt.area / n_points))
    to_pred = SampleIndex(p_pts, spacing_m=math.sqrt(pred.area / n_points))
    if deadline is not None:  # built before the first chunk, whose pace would otherwise count their set-up
        to_gt.build()
        to_pred.build()
    (d_pg, i_pg), (d_gp, i_gp) = _measure_until(lambda a, b: (to_gt.query(p_pts[a:b]), to_pred.query(g_pts[a:b])),
                                                int(n_points), deadline, clock)
    queries = len(d_pg)
    precision = float(np.mean(d_pg < fscore_threshold_m))
    recall = float(np.mean(d_gp < fscore_threshold_m))
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    normal = 0.5 * (_mean_angle_deg(p_nrm[:queries], g_nrm[i_pg]) + _mean_angle_deg(g_nrm[:queries], p_nrm[i_gp]))
    acc, comp = float(d_pg.mean()) * 1e3, float(d_gp.mean()) * 1e3
    return MeshMetrics(chamfer_mm=0.5 * (acc + comp), accuracy_mm=acc, completeness_mm=comp, fscore_5mm=fscore,
                       precision=precision, recall=recall, normal_error_deg=normal,
                       fscore_threshold_mm=fscore_threshold_m * 1e3, n_points=int(n_points), seed=int(seed),
                       queries=queries)


def _measure_until(measure: Callable[[int, int], tuple], n: int, deadline: float | None,
                   clock: Callable[[], float]) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """`measure(a, b)` (each side's (distances, indices) for samples a..b) over 0..n: at once without a deadline,
    else in chunks doubling from FIRST_QUERIES while the last chunk's pace says the next ends by `deadline`."""
    if deadline is None:
        return measure(0, n)
    parts, done, size = [], 0, min(FIRST_QUERIES, n)
    while done < n:
        t0 = clock()
        parts.append(measure(done, done + size))
        took, done = clock() - t0, done + size
        size, last = min(2 * size, n - done), size
        if clock() + took * size / last > deadline:
            break
    return tuple(tuple(np.concatenate([p[side][k] for p in parts]) for k in range(2)) for side in range(2))


def _mean_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Mean unsigned angle (degrees) between unit vectors a (n, 3) and b (n, 3)."""
    cos = np.clip(np.abs(np.einsum("ij,ij->i", a, b)), 0.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean())


ON_WALL_M = 1e-12
"""A corner this close to a crop box's wall (metres) lies on it: a corner a rounding error inside would leave a long
sliver of no area along the wall, one a rounding error outside a cut of no length."""


def crop_to_box(mesh, box_min, box_max, what: str = "mesh"):
    """The surface of `mesh` inside the axis-aligned box [box_min, box_max] (metres, (3,) each; its walls count as
    inside): the faces wholly inside, and of every other face that overlaps the box, its part inside, clipped exactly
    at the walls. `what` names the mesh in errors ("ground truth", "reconstruction").

    Clipped, not kept or dropped whole (nor by corners or centroids): a ground truth of large CAD faces and a fine
    reconstruction of the same surface are then scored over the same part of it, and a large face that passes
    through the box with every corner and its centroid outside (a wall across a band) is cut, not lost.

    Used to evaluate an object apart from what surrounds it (a table top, a floor slab in the ground truth).
    """
    import trimesh

    check_mesh(mesh, what)
    lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise MeshError(f"crop box corners must be finite 3-vectors, got {lo.tolist()} and {hi.tolist()}")
    if np.any(lo >= hi):
        raise MeshError(f"crop box min {lo.tolist()} must lie below max {hi.tolist()} on every axis (m)")

    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    tri = vertices[faces]  # (F, 3, 3)
    whole = np.all((tri >= lo) & (tri <= hi), axis=(1, 2))
    overlaps = ~whole & np.all((tri.min(axis=1) <= hi) & (tri.max(axis=1) >= lo), axis=1)
    pieces, src = tri[overlaps], faces[overlaps]
    for axis in range(3):
        pieces, src = _clip_half_space(pieces, src, axis, lo[axis], 1.0)
        pieces, src = _clip_half_space(pieces, src, axis, hi[axis], -1.0)
    # A face touching a wall from outside leaves a piece of no area (its corners on the wall, one point or an edge).
    solid = np.linalg.norm(np.cross(pieces[:, 1] - pieces[:, 0], pieces[:, 2] - pieces[:, 0]), axis=1) > 0
    pieces, src = pieces[solid], src[solid]
    if not (whole.any() or len(pieces)):
        raise MeshError(f"{what}: no triangle lies inside the crop box {lo.tolist()} .. {hi.tolist()} m "
                        f"(its bounds {np.round(mesh.bounds, 4).tolist()} m)")
    # The clip's new corners, one vertex per position: faces that shared an edge share its cut point (computed alike
    # on both, see _cut_points), so the cropped surface stays connected along the walls.
    new = src < 0
    new_points, index = np.unique(pieces[new], axis=0, return_inverse=True)
    src[new] = len(vertices) + index.reshape(-1)
    out = trimesh.Trimesh(np.concatenate([vertices, new_points]), np.concatenate([faces[whole], src]), process=False)
    out.remove_unreferenced_vertices()
    return out


def _clip_half_space(tri: np.ndarray, src: np.ndarray, axis: int, bound: float,
                     sign: float) -> tuple[np.ndarray, np.ndarray]:
    """The parts of triangles `tri` (T, 3, 3) where sign * (x[axis] - bound) >= 0, as triangles in the same winding.
    `src` (T, 3) holds each corner's vertex index in the source mesh, -1 for a corner made by a cut."""
    d = sign * (tri[:, :, axis] - bound)
    d[np.abs(d) <= ON_WALL_M] = 0.0
    inside = d >= 0
    count = inside.sum(axis=1)
    out_tri, out_src = [tri[count == 3]], [src[count == 3]]
    for n_in in (1, 2):
        pick = count == n_in
        t, s, dd = tri[pick], src[pick], d[pick]
        r = np.arange(len(t))
        # One inside: that corner a keeps a triangle. Two inside: the outside corner a is cut off, leaving a quad.
        a = np.argmax(inside[pick], axis=1) if n_in == 1 else np.argmin(inside[pick], axis=1)
        b, c = (a + 1) % 3, (a + 2) % 3
        if n_in == 1:
            (xb, sb), (xc, sc) = (_cut_points(t[r, a], t[r, e], dd[r, a], dd[r, e], s[r, a], axis, bound)
                                  for e in (b, c))
            out_tri.append(np.stack([t[r, a], xb, xc], axis=1))
            out_src.append(np.stack([s[r, a], sb, sc], axis=1))
        else:
            (xb, sb), (xc, sc) = (_cut_points(t[r, e], t[r, a], dd[r, e], dd[r, a], s[r, e], axis, bound)
                                  for e in (b, c))
            out_tri += [np.stack([xb, t[r, b], t[r, c]], axis=1), np.stack([xb, t[r, c], xc], axis=1)]
            out_src += [np.stack([sb, s[r, b], s[r, c]], axis=1), np.stack([sb, s[r, c], sc], axis=1)]
    return np.concatenate(out_tri), np.concatenate(out_src)


def _cut_points(p_in: np.ndarray, q_out: np.ndarray, d_in: np.ndarray, d_out: np.ndarray, s_in: np.ndarray,
                axis: int, bound: float) -> tuple[np.ndarray, np.ndarray]:
    """Where the edges from p_in (inside, distance d_in >= 0) to q_out (outside, d_out < 0) cross the plane
    x[axis] = bound, and their source indices: p_in's own (`s_in`) where it lies on the wall, else -1. Always
    computed from the inside end, so two faces sharing an edge get the very same point."""
    on_wall = d_in == 0
    t = d_in / (d_in - d_out)
    x = p_in + t[:, None] * (q_out - p_in)
    x[:, axis] = np.where(on_wall, p_in[:, axis], bound)  # on the wall exactly, not a rounding off it
    return x, np.where(on_wall, s_in, -1)
