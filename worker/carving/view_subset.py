"""An evenly spread subset of a large capture's views, for the set-up stages whose cost grows with the views.

Space carving and the empty-space weights test every view against every cell or node: O(views x cells). The fit
itself samples a fixed number of views a step and does not grow with them, so a 2000-view capture spent minutes in
set-up (52 s carving, 47 s in the first step's empty-space weights, on a shared 2-core machine) and made one
step in a 120 s budget. Those stages read at most `MAX_SETUP_VIEWS` views, chosen to spread evenly over the
views' positions and directions (farthest-point sampling, which up to ties does not depend on the order the views
were taken in: an adaptive scan orders its views by rank, so the first ones are no even spread). What the subset
changes:

- carving with fewer views proves less space empty: a looser hull, which the fit carves further (every view's
  histograms still speak in training). Carving's rule that space fewer than MIN_VIEWS views see was never scanned
  keeps, of a subset, what one of its views sees (`fast/problem.py`): counted among the subset, it dropped a part
  that only a cluster of views sees (an adaptive scan gathers them where the fit is unsure; the subset takes one);
- the share of views that see a node (on a table) and the number that hear a return there (without one) are those
  of a capture of `MAX_SETUP_VIEWS` views, the regime those rules were tuned in.

Captures of `MAX_SETUP_VIEWS` views or fewer pass through untouched: their set-up is the same as before.
"""

from __future__ import annotations

import numpy as np

from spadscan.protocol.errors import CaptureError

MAX_SETUP_VIEWS = 256
"""Views the O(views x cells) set-up stages read at most: the largest validated captures' size, so a capture of up
to 256 views is set up as before and one of 257 from nearly the same views (128 would set it up from fewer views than
a 256-view capture). A simulated 2000-view TMF8820 sphere, 120 s, one thread: 1 step and 31.6 mm read whole; 1,336
steps and 0.76 mm at 256; 913 steps and 0.92 mm at 512 (benchmarks/RESULTS.md)."""


def spread_views(poses, max_views: int | None = None, usable=None) -> np.ndarray:
    """(k,) sorted indices of at most `max_views` (None: `MAX_SETUP_VIEWS`) views spread evenly over the capture.

    poses (V, 4, 4) sensor-to-world (metres, +z boresight). usable (V, Z) bool or None: a view none of whose zones
    holds data proves nothing and sees nothing, so it is never picked. A capture of `max_views` views or fewer comes
    back whole (all V indices, views without data included: nothing changes for it). Otherwise farthest-point
    sampling over each view's position (about the views' centroid, in units of their rms distance from it) and
    boresight direction: it starts at the view farthest from the centroid of those features and adds, one at a time,
    the view farthest from every view picked so far. Deterministic; ties go to the lower index.
    """
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] != (4, 4) or not np.all(np.isfinite(p[:, :3, :])):
        raise CaptureError(f"poses must be finite (V, 4, 4) sensor-to-world matrices, got shape {p.shape}")
    limit = MAX_SETUP_VIEWS if max_views is None else max_views
    if not (isinstance(limit, (int, np.integer)) and limit >= 1):
        raise CaptureError(f"the set-up's view limit {limit} must be an integer >= 1")
    n = len(p)
    if n <= limit:
        return np.arange(n)
    candidates = np.arange(n)
    if usable is not None:
        held = np.asarray(usable, bool).reshape(n, -1).any(axis=1)
        candidates = np.flatnonzero(held)
        if len(candidates) <= limit:
            return candidates
    return candidates[_farthest_points(_features(p[candidates]), limit)]


def _features(p: np.ndarray) -> np.ndarray:
    """(V, 6) per view: position less the views' centroid over their rms distance from it (a unitless spread, the
    rig's scale and placement removed), and the unit boresight. Both parts span about 2 across a sphere of views."""
    pos = p[:, :3, 3] - p[:, :3, 3].mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum(pos * pos, axis=1))))
    pos = pos / scale if scale > 0 else pos
    axis = p[:, :3, 2]
    norm = np.linalg.norm(axis, axis=1, keepdims=True)
    return np.concatenate([pos, axis / np.where(norm > 0, norm, 1.0)], axis=1)


def _farthest_points(features: np.ndarray, k: int) -> np.ndarray:
    """(k,) sorted row indices of `features` (V, F), V > k, picked by farthest-point sampling: O(V k)."""
    first = int(np.argmax(np.sum((features - features.mean(axis=0)) ** 2, axis=1)))
    picked = [first]
    dist = np.sum((features - features[first]) ** 2, axis=1)
    dist[first] = -1.0  # never again, even where repeated poses leave every distance 0
    for _ in range(k - 1):
        nxt = int(np.argmax(dist))
        picked.append(nxt)
        dist = np.minimum(dist, np.sum((features - features[nxt]) ** 2, axis=1))
        dist[nxt] = -1.0
    return np.sort(np.asarray(picked))


__all__ = ["MAX_SETUP_VIEWS", "spread_views"]
