"""Ranking candidate sensor poses by how much each would tell the live model that it does not know yet.

The live job calls `update_next_views` every few seconds while an adaptive scan runs: it ranks the scan's candidate
poses (`protocol.next_views.candidate_poses`) with `rank_candidates` and writes the capture's next_views.json, which
the daemon reads before each pose. Three measures, each a score per candidate (higher: more useful):

- `coverage` (the default): how much of the current surface the view would see that the views taken have seen
  little. The surface (the latest field's zero level, above the floor) is cut into patches; a view *sees* a patch
  when the patch lies in one of its zones, faces it, and nothing of the field stands between them. A patch seen by
  views with incidence cosines c_1, c_2, ... holds information I = sum c_i, and its uncertainty is taken as 1 / (1 + I);
  a candidate's score is the area-weighted drop of that uncertainty it would bring, sum area x (1/(1 + I) -
  1/(1 + I + c)). Regions of the carved hull no view has constrained (I = 0) weigh most.
- `disagreement`: how far apart the recent field snapshots put the surface along the candidate's rays (the variance
  of the first-hit range between snapshots, weighted by each ray's solid angle): where the shape is still moving.
- `sensitivity`: how much the candidate's predicted histogram changes between the snapshots, against its photon
  noise: sum over bins of (h_latest - h_older)^2 / (h_mean + background), with h from the first hits of each snapshot
  (cos / r^2 per steradian, the sensor's signal scale, cycles and pulse).

`benchmarks/next_best_view.py` measures which one buys the most (Chamfer against views taken). Every score is finite;
a candidate that sees nothing scores 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from spadscan.protocol.next_views import candidate_poses, ranked, write_next_views
from spadscan.protocol.raycast import zone_rays

from .field_trace import TracedField
from .snapshot import LiveSnapshot

MEASURES = ("coverage", "disagreement", "sensitivity")
DEFAULT_MEASURE = "coverage"
RAYS_PER_VIEW = 96
"""Rays traced per candidate for the ray-based measures, shared by the zones (at least 8 per zone)."""
SURFACE_POINTS = 1500
"""Surface patches the coverage measure weighs."""
MIN_COS = 0.1
"""A patch seen more obliquely than this (incidence cosine) is not seen: its return is weak and smeared."""


def is_adaptive(manifest: dict) -> bool:
    """Whether the capture's scan chooses its views from next_views.json (its manifest's schedule record says
    'adaptive'): only then does the live job rank candidates and write that file."""
    schedule = manifest.get("schedule") if isinstance(manifest, dict) else None
    return isinstance(schedule, dict) and schedule.get("schedule") == "adaptive"


def update_next_views(capture: Path, manifest: dict, snapshot: LiveSnapshot | None,
                      measure: str = DEFAULT_MEASURE) -> Path | None:
    """Rank the scan's candidate poses from `snapshot` and write them as the capture's next_views.json
    (atomically); returns its path, or None when there is no snapshot yet. `pose_count` in the file is the number of
    views the snapshot's model was fitting (the daemon judges freshness by it)."""
    if snapshot is None:
        return None
    candidates = candidate_poses(manifest["schedule"])
    scores = rank_candidates(snapshot, candidates, measure)
    return write_next_views(capture, ranked(candidates, scores, len(snapshot.poses), measure))


def rank_candidates(snapshot: LiveSnapshot, candidates: np.ndarray, measure: str = DEFAULT_MEASURE) -> np.ndarray:
    """Scores (n,) float64 for candidate sensor poses `candidates` (n, 4, 4) sensor-to-world, metres: higher is a
    more useful next view (see the module docstring for the measures). Finite for every candidate; a candidate
    that sees nothing of the surface scores 0."""
    cand = np.asarray(candidates, float)
    if cand.ndim != 3 or cand.shape[1:] != (4, 4):
        raise ValueError(f"candidates must be (n, 4, 4) poses, got shape {cand.shape}")
    if measure not in MEASURES:
        raise ValueError(f"measure {measure!r} must be one of {', '.join(MEASURES)}")
    if len(cand) == 0:
        return np.zeros(0)
    with torch.no_grad():
        if measure == "coverage":
            scores = _coverage(snapshot, cand)
        else:
            scores = _ray_measure(snapshot, cand, measure)
    return np.nan_to_num(np.asarray(scores, np.float64), nan=0.0, posinf=0.0, neginf=0.0)


# ---- coverage ---------------------------------------------------------------------------------------------------------
def _coverage(snap: LiveSnapshot, cand: np.ndarray) -> np.ndarray:
    field = TracedField(snap.latest.grid)
    points, normals, area = field.surface(snap.floor_z, SURFACE_POINTS)
    if len(points) == 0:
        return np.zeros(len(cand))
    info = _seen_cos(field, snap.sensor, points, normals, snap.poses).sum(axis=0)  # (M,) over the views taken
    c = _seen_cos(field, snap.sensor, points, normals, cand)  # (n, M)
    gain = 1.0 / (1.0 + info) - 1.0 / (1.0 + info + c)
    return gain @ area


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
    ok = (cos > MIN_COS) & _in_zones(sensor, local)
    view, patch = np.nonzero(ok)
    if len(view) == 0:
        return out
    start = torch.as_tensor(points[patch] + normals[patch] * 1.5 * field.voxel, dtype=torch.float32)
    d = torch.as_tensor(to_sensor[view, patch] / dist[view, patch, None], dtype=torch.float32)
    reach = torch.as_tensor(dist[view, patch] - 1.5 * field.voxel, dtype=torch.float32)
    blocked = field.trace(start, d, reach, normals=False).hit.numpy()
    out[view[~blocked], patch[~blocked]] = cos[view, patch][~blocked]
    return out


def _in_zones(sensor, local: np.ndarray) -> np.ndarray:
    """(...,) whether directions `local` (..., 3) in the sensor's frame fall in any of its zones."""
    z = local[..., 2]
    seen = np.zeros(local.shape[:-1], dtype=bool)
    front = z > 1e-9
    unit = local / np.maximum(np.linalg.norm(local, axis=-1, keepdims=True), 1e-12)
    for zone in sensor.zones:
        if zone.kind == "cone":
            seen |= unit @ np.asarray(zone.axis, float) >= np.cos(zone.half_angle_rad)
        else:
            x, y = local[..., 0] / np.where(front, z, 1), local[..., 1] / np.where(front, z, 1)
            seen |= front & (zone.tan_x[0] <= x) & (x <= zone.tan_x[1]) & (zone.tan_y[0] <= y) & (y <= zone.tan_y[1])
    return seen


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
    t_max = float(sensor.n_bins * sensor.bin_width_m)
    hits = [TracedField(f.grid).trace(o, d, t_max) for f in snap.fields]
    if len(hits) < 2:
        return np.zeros(n)
    if measure == "disagreement":
        t = torch.stack([h.t for h in hits]).numpy().reshape(len(hits), n, r)
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
    b = np.floor(sensor.zero_bin + t / sensor.bin_width_m).astype(np.int64)
    keep = hit & (b >= 0) & (b < sensor.n_bins)
    idx = np.repeat(np.arange(n), r) * sensor.n_zones + np.tile(zone, n)
    out = np.zeros((n * sensor.n_zones, sensor.n_bins))
    np.add.at(out, (idx[keep], b[keep]), value[keep])
    kernel, origin = sensor.pulse.kernel(1)
    full = np.apply_along_axis(lambda h: np.convolve(h, kernel), 1, out)
    return full[:, origin: origin + sensor.n_bins].reshape(n, sensor.n_zones, sensor.n_bins)


__all__ = ["rank_candidates", "is_adaptive", "update_next_views", "MEASURES", "DEFAULT_MEASURE"]
