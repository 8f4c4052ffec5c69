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
FIRST_QUERIES = 5_000
"""Samples per mesh whose distances are measured before a deadline is looked at: the fewest that metrics stopped
by one rest on. Later chunks double."""


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


def sample_surface(mesh, n_points: int, rng: np.random.Generator,
                   smooth: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Sample points uniformly by area. Returns points (n, 3) metres and unit normals (n, 3): their faces' normals,
    or with `smooth` the mesh's vertex normals interpolated across the face (the SDF gradient, for our meshes)."""
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
    if not smooth:
        return points, cross[face] / double_area[face, None]  # sampled faces have area > 0 by construction
    corner = np.asarray(mesh.vertex_normals, dtype=np.float64)[np.asarray(mesh.faces)[face]]  # (n, 3, 3)
    normals = (1 - u - v)[:, None] * corner[:, 0] + u[:, None] * corner[:, 1] + v[:, None] * corner[:, 2]
    return points, normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def vertex_normal_error_deg(mesh, gt, n_gt: int = 300_000, seed: int = 0) -> np.ndarray:
    """Per-vertex angle (degrees) between the mesh's vertex normal and the ground truth's normal at the nearest of
    n_gt area-uniform ground-truth samples (vertex normals interpolated), using |<n, n~>| (orientation-free, as in
    the paper). (n_vertices,)."""
    check_mesh(mesh, "reconstruction")
    check_mesh(gt, "ground truth")
    g_pts, g_nrm = sample_surface(gt, int(n_gt), np.random.default_rng(seed), smooth=True)
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


CROP_SPLIT_M = 0.002
"""Faces across a crop box's walls are split to this size (metres) before they are kept or dropped by their
centroids: a cut by whole triangles would keep or drop up to a coarse face's size beyond it, so that a ground truth
of large CAD faces and a fine reconstruction of the same surface were scored over different parts of it."""


def crop_to_box(mesh, box_min, box_max):
    """The surface of `mesh` inside the axis-aligned box [box_min, box_max] (metres, (3,) each), to CROP_SPLIT_M:
    the faces wholly inside, and the pieces (split to that size) whose centroids lie inside of those across its
    walls.

    Used to evaluate an object apart from what surrounds it (a table top, a floor slab in the ground truth).
    """
    import trimesh

    check_mesh(mesh, "mesh to crop")
    lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise MeshError(f"crop box corners must be finite 3-vectors, got {lo.tolist()} and {hi.tolist()}")
    if np.any(lo >= hi):
        raise MeshError(f"crop box min {lo.tolist()} must lie below max {hi.tolist()} on every axis (m)")

    def inside(points):
        return np.all((points >= lo) & (points <= hi), axis=-1)

    corners = inside(mesh.vertices)[mesh.faces]
    whole = corners.all(axis=1)
    across = ~whole & (corners.any(axis=1) | inside(mesh.triangles_center))
    faces = [mesh.faces[whole]]
    vertices = [mesh.vertices]
    if across.any():
        pieces = trimesh.Trimesh(mesh.vertices, mesh.faces[across], process=False)
        pieces.remove_unreferenced_vertices()
        pieces = pieces.subdivide_to_size(CROP_SPLIT_M, max_iter=12)
        keep = inside(pieces.triangles_center)
        faces.append(pieces.faces[keep] + len(mesh.vertices))
        vertices.append(pieces.vertices)
    kept = np.concatenate(faces)
    if not len(kept):
        raise MeshError(f"no triangle lies inside the crop box {lo.tolist()} .. {hi.tolist()} m "
                        f"(mesh bounds {mesh.bounds.tolist()})")
    out = trimesh.Trimesh(np.concatenate(vertices), kept, process=False)
    out.remove_unreferenced_vertices()
    return out
