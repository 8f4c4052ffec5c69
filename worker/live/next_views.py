"""Ranking candidate sensor poses by how much each would tell the live model that it does not know yet.

The live job calls `update_next_views` every few seconds while an adaptive scan runs: it ranks the scan's candidate
poses (`protocol.next_views.candidate_poses`) with `rank_candidates` and writes the capture's next_views.json, which
the daemon reads before each pose. Three measures, each a score per candidate (higher: more useful):

- `coverage` (the default): how much of the current surface the view would see that the views taken have seen
  little. The surface (the latest field's zero level, above the floor) is cut into patches; a view *sees* a patch
  when the patch lies in one of its zones, faces it, and nothing of the field stands between them. A patch seen by
  views with incidence cosines c_1, c_2, ... holds information I = sum c_i, and its uncertainty is taken as 1 / (1 + I);
  a candidate's score is the area-weighted drop of that uncertainty it would bring, sum area x (1/(1 + I) -
  1/(1 + I + c)). Regions of the carved hull no view has constrained (I = 0) weigh most. With `unseen_space`,
  space no view has seen counts too: cells inside the carved hull that the field calls empty (where a fit is free to keep spurious surface)
  are patches with I = 0 that a candidate sees (c = 1) when they lie in its zones and range with nothing of the
  field between, all of them together weighing at most as much as the surface.
- `disagreement`: how far apart the recent field snapshots put the surface along the candidate's rays (the variance
  of the first-hit range between snapshots, weighted by each ray's solid angle): where the shape is still moving.
- `sensitivity`: how much the candidate's predicted histogram changes between the snapshots, against its photon
  noise: sum over bins of (h_latest - h_older)^2 / (h_mean + background), with h from the first hits of each snapshot
  (cos / r^2 per steradian, the sensor's signal scale, cycles and pulse).

Every measure is then spread: the daemon takes several views from one ranking, and views that each see much but
from nearly the same side leave the space around the object seen by no view, where the fit keeps spurious surface.
So the ranking is built greedily: each next place goes to the candidate whose measure, times a spread factor
1 - exp(-(a / a0)^2), is highest, where a is its angle to the nearest view taken or ranked ahead of it and a0 half
the spacing that evenly spread views (those taken and ranked so far, plus one) would have over the candidates'
band; after each pick the coverage measure counts that view's patches as seen. `spread=False` ranks by the measure
alone.

`benchmarks/next_best_view.py` measures which one buys the most (Chamfer against views taken). Every score is finite;
a candidate that sees nothing scores 0.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from spadscan.protocol.next_views import candidate_poses, ranked, write_next_views
from spadscan.protocol.raycast import zone_rays
from spadscan.protocol.sensor_model import in_any_zone

from .field_trace import TracedField
from .snapshot import LiveSnapshot

MEASURES = ("coverage", "disagreement", "sensitivity")
DEFAULT_MEASURE = "coverage"
RAYS_PER_VIEW = 96
"""Rays traced per candidate for the ray-based measures, shared by the zones (at least 8 per zone)."""
SURFACE_POINTS = 1500
"""Surface patches the coverage measure weighs."""
UNSEEN_CELLS = 1500
"""Cells of unseen space (inside the carved hull, outside the surface) the coverage measure weighs."""
SPREAD_PICKS = 64
"""Places of the ranking filled greedily with the spread factor (more than any scan takes from one ranking); the
candidates after them keep the spread score the next pick would see, scaled below the last pick."""
MIN_COS = 0.1
"""A patch seen more obliquely than this (incidence cosine) is not seen: its return is weak and smeared."""


def is_adaptive(manifest: dict) -> bool:
    """Whether the capture's scan chooses its views from next_views.json (its manifest's schedule record says
    'adaptive'): only then does the live job rank candidates and write that file."""
    schedule = manifest.get("schedule") if isinstance(manifest, dict) else None
    return isinstance(schedule, dict) and schedule.get("schedule") == "adaptive"


def update_next_views(capture: Path, manifest: dict, snapshot: LiveSnapshot | None,
                      published: np.ndarray | None = None, measure: str = DEFAULT_MEASURE) -> Path | None:
    """Rank the scan's candidate poses from `snapshot` and write them as the capture's next_views.json
    (atomically); returns its path, or None when there is no snapshot yet.

    `published`: the sensor poses (V, 4, 4) of every view the scan has published (default: the snapshot's, those its
    model fits). The ranking counts them all as taken, and `pose_count` in the file is their number: the daemon
    calls a ranking stale once it is `next_views_max_lag` poses behind, and the model refits only every few views
    (a quarter more, up to 16), so a count of the fitted views would make every ranking between two refits stale."""
    if snapshot is None:
        return None
    if published is not None:
        snapshot = dataclasses.replace(snapshot, poses=np.asarray(published, float).reshape(-1, 4, 4))
    candidates = candidate_poses(manifest["schedule"])
    scores = rank_candidates(snapshot, candidates, measure)
    return write_next_views(capture, ranked(candidates, scores, len(snapshot.poses), measure))


def rank_candidates(snapshot: LiveSnapshot, candidates: np.ndarray, measure: str = DEFAULT_MEASURE,
                    spread: bool = True, unseen_space: bool = False) -> np.ndarray:
    """Scores (n,) float64 for candidate sensor poses `candidates` (n, 4, 4) sensor-to-world, metres: higher is a
    more useful next view (see the module docstring for the measures and the spread). Finite for every candidate; a
    candidate that sees nothing of the surface scores 0. `unseen_space` adds the unseen space to the coverage
    measure (off by default: it drew the bunny's views to the lowest elevations and made its fits worse)."""
    cand = np.asarray(candidates, float)
    if cand.ndim != 3 or cand.shape[1:] != (4, 4):
        raise ValueError(f"candidates must be (n, 4, 4) poses, got shape {cand.shape}")
    if measure not in MEASURES:
        raise ValueError(f"measure {measure!r} must be one of {', '.join(MEASURES)}")
    if len(cand) == 0:
        return np.zeros(0)
    with torch.no_grad():
        if measure == "coverage":
            gain = _coverage(snapshot, cand, unseen_space)
        else:
            gain = _StaticGain(_ray_measure(snapshot, cand, measure))
    if not spread:
        return _finite(gain.scores())
    return _spread_ranking(gain, cand, np.asarray(snapshot.poses, float).reshape(-1, 4, 4))


def _finite(scores) -> np.ndarray:
    return np.nan_to_num(np.asarray(scores, np.float64), nan=0.0, posinf=0.0, neginf=0.0)


# ---- spread -----------------------------------------------------------------------------------------------------------
class _StaticGain:
    """A measure that taking a view does not change (the ray measures)."""

    def __init__(self, scores: np.ndarray):
        self._scores = _finite(scores)

    def scores(self) -> np.ndarray:
        return self._scores

    def take(self, i: int) -> None:
        pass


def _spread_ranking(gain, cand: np.ndarray, taken: np.ndarray) -> np.ndarray:
    """Greedy spread scores (module docstring): decreasing along the greedy order, 0 where the measure is 0."""
    axes = _unit(cand[:, :3, 2])
    nearest = np.full(len(cand), np.pi)  # radians to the nearest view taken or ranked ahead
    if len(taken):
        nearest = _angles(axes, _unit(taken[:, :3, 2])).min(axis=1)
    omega = _band_solid_angle(axes)
    views = len(taken)
    out = np.zeros(len(cand))
    free = np.ones(len(cand), dtype=bool)
    last = np.inf

    def values() -> np.ndarray:  # each free candidate's gain times its spread factor, given the picks so far
        a0 = 0.5 * np.sqrt(omega / (views + 1))
        return np.where(free, np.maximum(_finite(gain.scores()), 0.0) * (1.0 - np.exp(-(nearest / a0) ** 2)), 0.0)

    for _ in range(min(len(cand), SPREAD_PICKS)):
        value = values()
        i = int(np.argmax(value))
        if value[i] <= 0.0:
            break
        # Strictly below the pick before (by one ulp where its value is no lower): next_views.json is sorted by score,
        # and a tie would put the later pick first where its candidate index is lower.
        last = float(value[i]) if value[i] < last else float(np.nextafter(last, 0.0))
        out[i], free[i] = last, False
        nearest = np.minimum(nearest, _angles(axes, axes[i:i + 1])[:, 0])
        views += 1
        gain.take(i)
    # The rest in the order the next greedy pick would see them: after the last pick's own effect (ranked by the
    # value before it, the candidates beside the last pick led them, though it had just covered what they see).
    rest = values()
    if np.isfinite(last) and rest.max() > 0:
        rest *= min(1.0, 0.999 * last / rest.max())  # below the last greedy pick, in their own order
    return np.where(free, rest, out)


def _band_solid_angle(axes: np.ndarray) -> float:
    """Steradians the candidates' viewing directions cover: each owns a hexagonal cell of its nearest-neighbour
    spacing (Fibonacci candidates); 4 pi at most."""
    if len(axes) < 2:
        return 4 * np.pi
    ang = _angles(axes, axes)
    np.fill_diagonal(ang, np.inf)
    spacing = float(np.median(ang.min(axis=1)))
    return float(min(4 * np.pi, len(axes) * np.sqrt(3) / 2 * spacing ** 2))


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip(a @ b.T, -1.0, 1.0))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


# ---- coverage ---------------------------------------------------------------------------------------------------------
class _CoverageGain:
    """The coverage measure (module docstring); `take` counts a view's patches as seen."""

    def __init__(self, info: np.ndarray, c: np.ndarray, area: np.ndarray):
        self.info, self.c, self.area = info, c, area

    def scores(self) -> np.ndarray:
        if self.c.shape[1] == 0:
            return np.zeros(len(self.c))
        return (1.0 / (1.0 + self.info) - 1.0 / (1.0 + self.info + self.c)) @ self.area

    def take(self, i: int) -> None:
        self.info = self.info + self.c[i]


def _coverage(snap: LiveSnapshot, cand: np.ndarray, unseen_space: bool) -> _CoverageGain:
    field = TracedField(snap.latest.grid)
    points, normals, area = field.surface(snap.floor_z, SURFACE_POINTS)
    if len(points) == 0:
        return _CoverageGain(np.zeros(0), np.zeros((len(cand), 0)), np.zeros(0))
    info = _seen_cos(field, snap.sensor, points, normals, snap.poses).sum(axis=0)  # (M,) over the views taken
    c = _seen_cos(field, snap.sensor, points, normals, cand)  # (n, M)
    area = np.asarray(area, float)
    cells, cell_area = _unconstrained(snap, float(area.sum())) if unseen_space else (np.zeros((0, 3)), 0.0)
    if len(cells):  # unseen space: patches no view has seen (I = 0), seen head-on (c = 1) by the candidates that see them
        info = np.concatenate([info, np.zeros(len(cells))])
        c = np.concatenate([c, _sees_cells(field, snap.sensor, cells, cand)], axis=1)
        area = np.concatenate([area, np.full(len(cells), cell_area)])
    return _CoverageGain(info, c, area)


def _sees_cells(field: TracedField, sensor, cells: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(len(poses), U) 1.0 where a pose sees the point `cells` (U, 3): in one of its zones, within the sensor's
    range and nothing of the field between them."""
    to_sensor = poses[:, None, :3, 3] - cells[None]  # (n, U, 3)
    dist = np.linalg.norm(to_sensor, axis=-1)
    local = np.matmul(-to_sensor, poses[:, :3, :3])
    ok = in_any_zone(sensor.zones, local) & (dist < sensor.max_range_m)  # the last bin's range, past zero_bin
    out = np.zeros(ok.shape)
    view, cell = np.nonzero(ok)
    if len(view):
        start = torch.as_tensor(cells[cell], dtype=torch.float32)
        d = torch.as_tensor(to_sensor[view, cell] / dist[view, cell, None], dtype=torch.float32)
        blocked = field.trace(start, d, torch.as_tensor(dist[view, cell], dtype=torch.float32), normals=False).hit
        out[view[~blocked.numpy()], cell[~blocked.numpy()]] = 1.0
    return out


def _unconstrained(snap: LiveSnapshot, surface_area: float) -> tuple[np.ndarray, float]:
    """Cells of the carved hull (no view proved them empty) that the latest field calls empty, more than two cells
    from its surface and above the floor: where a fit is free to put spurious surface. Their centres (U, 3), at most
    UNSEEN_CELLS of them, and the area each stands for: a cell face each, but all of them together no more than the
    surface's area (m^2), so that unseen space and unseen surface weigh alike."""
    hull = snap.hull
    k, j, i = np.nonzero(hull.sdf < 0)
    if len(i) == 0 or surface_area <= 0:
        return np.zeros((0, 3)), 0.0
    centres = hull.origin + hull.voxel_m * np.stack([i, j, k], axis=1)
    keep = snap.latest.grid.sample(centres) > 2 * hull.voxel_m
    if snap.floor_z is not None:
        keep &= centres[:, 2] > snap.floor_z + hull.voxel_m
    centres = centres[keep]
    if len(centres) == 0:
        return np.zeros((0, 3)), 0.0
    total = min(len(centres) * hull.voxel_m ** 2, surface_area)
    if len(centres) > UNSEEN_CELLS:
        centres = centres[np.random.default_rng(0).choice(len(centres), UNSEEN_CELLS, replace=False)]
    return centres, total / len(centres)


def _seen_cos(field: TracedField, sensor, points: np.ndarray, normals: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(len(poses), M) incidence cosine of each surface patch as each pose sees it, 0 where it does not."""
    out = np.zeros((len(poses), len(points)))
    if len(poses) == 0:
        return out
    points, normals = points.astype(np.float32), normals.astype(np.float32)
    o = poses[:, :3, 3].astype(np.float32)
    to_sensor = o[:, None, :] - points[None]  # (n, M, 3)
    dist = np.sqrt(np.einsum("nmk,nmk->nm", to_sensor, to_sensor))
    cos = np.einsum("nmk,mk->nm", to_sensor, normals) / np.maximum(dist, 1e-12)
    local = np.matmul(-to_sensor, poses[:, :3, :3].astype(np.float32))  # patch in each sensor's frame
    ok = (cos > MIN_COS) & in_any_zone(sensor.zones, local)
    view, patch = np.nonzero(ok)
    if len(view) == 0:
        return out
    start = torch.as_tensor(points[patch] + normals[patch] * 1.5 * field.voxel, dtype=torch.float32)
    d = torch.as_tensor(to_sensor[view, patch] / dist[view, patch, None], dtype=torch.float32)
    reach = torch.as_tensor(dist[view, patch] - 1.5 * field.voxel, dtype=torch.float32)
    blocked = field.trace(start, d, reach, normals=False).hit.numpy()
    out[view[~blocked], patch[~blocked]] = cos[view, patch][~blocked]
    return out


# ---- the ray measures -----------------------------------------------------------------------------------------------
def _ray_measure(snap: LiveSnapshot, cand: np.ndarray, measure: str) -> np.ndarray:
    """disagreement or sensitivity (module docstring) from the first hits of each snapshot along every candidate's
    rays."""
    sensor = snap.sensor
    rays = zone_rays(sensor.zones, max(8, RAYS_PER_VIEW // sensor.n_zones), 0)
    dirs, w = rays.directions.reshape(-1, 3), rays.weights.reshape(-1)  # (R, 3), (R,) steradians
    zone = np.repeat(np.arange(sensor.n_zones), rays.n_rays)
    n, r = len(cand), len(dirs)
    o = torch.as_tensor(np.repeat(cand[:, :3, 3], r, axis=0), dtype=torch.float32)
    d = torch.as_tensor(np.einsum("nij,rj->nri", cand[:, :3, :3], dirs).reshape(-1, 3), dtype=torch.float32)
    t_max = float(sensor.max_range_m)
    traced = [TracedField(f.grid) for f in snap.fields]
    hits = [f.trace(o, d, t_max) for f in traced]
    if len(hits) < 2:
        return np.zeros(n)
    if measure == "disagreement":
        # A miss reads where the ray leaves the newest snapshot's box, in every snapshot: where it leaves each one's
        # own box differs between refits that carved other hulls, which would score the box, not the surface.
        away = traced[-1].box_exit(o, d, t_max)
        t = torch.stack([torch.where(h.hit, h.t, away) for h in hits])
        t = t.numpy().reshape(len(hits), n, r)
        return (t.var(axis=0) * w).sum(axis=1)
    hists = np.stack([_histograms(sensor, h, d, w, zone, n) for h in hits])  # (S, n, Z, B)
    noise = hists.mean(axis=0) + max(sensor.background, 1e-12) * sensor.cycles
    return sum((((hists[-1] - h) ** 2) / noise).sum(axis=(1, 2)) for h in hists[:-1])


def _histograms(sensor, hits, d: torch.Tensor, w: np.ndarray, zone: np.ndarray, n: int) -> np.ndarray:
    """Expected signal counts (n, Z, B) of n candidates from their rays' first hits (albedo 1)."""
    r = len(w)
    hit = hits.hit.numpy()
    t = hits.t.numpy()
    cos = np.abs((hits.normal * d).sum(dim=-1).numpy())
    value = np.where(hit, np.tile(w, n) * cos / np.maximum(t, 1e-3) ** 2, 0.0) * sensor.signal_scale * sensor.cycles
    b = np.floor(sensor.bin_of_range(t)).astype(np.int64)
    keep = hit & (b >= 0) & (b < sensor.n_bins)
    idx = np.repeat(np.arange(n), r) * sensor.n_zones + np.tile(zone, n)
    out = np.zeros((n * sensor.n_zones, sensor.n_bins))
    np.add.at(out, (idx[keep], b[keep]), value[keep])
    kernel, origin = sensor.pulse.kernel(1)
    full = np.apply_along_axis(lambda h: np.convolve(h, kernel), 1, out)
    return full[:, origin: origin + sensor.n_bins].reshape(n, sensor.n_zones, sensor.n_bins)


__all__ = ["rank_candidates", "is_adaptive", "update_next_views", "MEASURES", "DEFAULT_MEASURE"]
