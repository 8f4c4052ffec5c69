"""Ranking candidate sensor poses by how much each would tell the live model that it does not know yet.

The live job calls `rank_candidates` every few seconds while an adaptive scan runs, with its latest snapshot and the
candidate poses, and writes the best ones into the capture's next_views.json.
"""

from __future__ import annotations

import numpy as np

from .snapshot import LiveSnapshot


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


__all__ = ["rank_candidates"]
