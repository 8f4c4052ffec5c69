"""Ranking candidate sensor poses by how much each would tell the live model that it does not know yet.

The live job calls `rank_candidates` every few seconds while an adaptive scan runs, with its latest snapshot and the
candidate poses, and writes the best ones into the capture's next_views.json.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .snapshot import LiveSnapshot


def is_adaptive(manifest: dict) -> bool:
    """Whether the capture's scan chooses its views from next_views.json (its manifest's schedule kind is
    'adaptive'): only then does the live job rank candidates and write that file."""
    schedule = manifest.get("schedule") if isinstance(manifest, dict) else None
    return isinstance(schedule, dict) and schedule.get("kind") == "adaptive"


def update_next_views(capture: Path, manifest: dict, snapshot: LiveSnapshot) -> Path | None:
    """Rank candidate poses for the scan in `capture` from `snapshot` and write them as the capture's
    next_views.json (atomically); returns its path, or None when nothing was written. The live job calls it every
    few seconds while an adaptive scan runs (`is_adaptive`).

    Placeholder until the candidates and the file format land: writes nothing."""
    return None


def rank_candidates(snapshot: LiveSnapshot, candidates: np.ndarray) -> np.ndarray:
    """Scores (n,) float64 for candidate sensor poses `candidates` (n, 4, 4) sensor-to-world, metres: higher is a
    more useful next view. Finite for every candidate; a candidate that sees nothing of the hull scores lowest.

    Placeholder ranking until the uncertainty measure lands: the spread of the recent field snapshots at the
    hull surface points each candidate's boresight meets first."""
    cand = np.asarray(candidates, float)
    if cand.ndim != 3 or cand.shape[1:] != (4, 4):
        raise ValueError(f"candidates must be (n, 4, 4) poses, got shape {cand.shape}")
    scores = np.zeros(len(cand))
    if len(cand) == 0:
        return scores
    grids = [f.grid for f in snapshot.fields]
    hull = snapshot.hull
    steps = np.linspace(0.0, snapshot.sensor.max_range_m, 64)
    for k, pose in enumerate(cand):
        pts = pose[:3, 3] + steps[:, None] * pose[:3, 2]
        inside = hull.sample(pts) < 0
        if not inside.any():
            scores[k] = -1.0
            continue
        p = pts[int(np.argmax(inside))]
        values = np.array([g.sample(p[None])[0] for g in grids])
        scores[k] = float(values.std()) if len(values) > 1 else 0.0
    return np.nan_to_num(scores, nan=-1.0)


__all__ = ["rank_candidates", "is_adaptive", "update_next_views"]
