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

A live fit rebuilds its model as views arrive, and a subset chosen afresh each time shared 29-48 % of its views with
the one before (each new view moves the farthest-point order), so every rebuild carved its hull and weighed its empty
space from other views. Given the views the last set-up read (`keep`), the subset keeps them and takes in a new view
only where it lies farther from the kept ones than the two closest kept views lie from each other, in place of one of
those two (`_swap_in`): the subset stays spread and changes little. A sphere of views ranked from the top down (as
an adaptive scan ranks them), arriving 100 at a time from 256 to 2000: 68-96 % of the subset stayed from one rebuild
to the next (afresh: 13-44 %), and no view lay more than 9.7 degrees from it (afresh: 9.2), at 0.01-0.1 s a rebuild.
"""

from __future__ import annotations

import numpy as np

from spadscan.protocol.errors import CaptureError

MAX_SETUP_VIEWS = 256
"""Views the O(views x cells) set-up stages read at most: the largest validated captures' size, so a capture of up
to 256 views is set up as before and one of 257 from nearly the same views (128 would set it up from fewer views than
a 256-view capture). A simulated 2000-view TMF8820 sphere, 120 s, one thread: 1 step and 31.6 mm read whole; 1,336
steps and 0.76 mm at 256; 913 steps and 0.92 mm at 512 (benchmarks/RESULTS.md)."""


def spread_views(poses, max_views: int | None = None, usable=None, keep=None) -> np.ndarray:
    """(k,) sorted indices of at most `max_views` (None: `MAX_SETUP_VIEWS`) views spread evenly over the capture.

    poses (V, 4, 4) sensor-to-world (metres, +z boresight). usable (V, Z) bool or None: a view none of whose zones
    holds data proves nothing and sees nothing, so it is never picked. A capture of `max_views` views or fewer comes
    back whole (all V indices, views without data included: nothing changes for it). Otherwise farthest-point
    sampling over each view's position (about the views' centroid, in units of their rms distance from it) and
    boresight direction: it starts at the view farthest from the centroid of those features and adds, one at a time,
    the view farthest from every view picked so far. Deterministic; ties go to the lower index.

    keep: indices of views picked before (a live fit's last set-up, of the capture as it then stood), or None. They
    stay picked (those with data; the farthest-point subset of them where more than `max_views`), the subset is
    filled up from the others by the same rule, and then takes in views that lie farther from it than its two
    closest views lie from each other, each in place of one of those two (`_swap_in`), at most as many as there are
    views that were not kept.
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
    features = _features(p[candidates])
    if keep is None:
        return candidates[_farthest_points(features, limit)]
    kept = np.flatnonzero(np.isin(candidates, np.asarray(keep, np.int64).reshape(-1)))
    if len(kept) > limit:
        kept = kept[_farthest_points(features[kept], limit)]
    picked = _fill_up(features, kept, limit)
    return np.sort(candidates[_swap_in(features, picked, rounds=len(candidates) - len(kept))])


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


def _fill_up(features: np.ndarray, picked: np.ndarray, k: int) -> np.ndarray:
    """(k,) row indices: `picked` (some rows of `features` (V, F), V >= k; none: the farthest-point start), then the
    rows farthest from every row picked so far, one at a time, as `_farthest_points` adds them."""
    if len(picked) == 0:
        return _farthest_points(features, k)
    picked = list(int(i) for i in picked)
    dist = np.min(_sq_dists(features, features[picked]), axis=1)
    dist[picked] = -1.0
    while len(picked) < k:
        nxt = int(np.argmax(dist))
        picked.append(nxt)
        dist = np.minimum(dist, np.sum((features - features[nxt]) ** 2, axis=1))
        dist[nxt] = -1.0
    return np.asarray(picked)


def _swap_in(features: np.ndarray, picked: np.ndarray, rounds: int) -> np.ndarray:
    """`picked` (k,) row indices of `features` (V, F), with up to `rounds` swaps: while the row farthest from the
    picked ones lies farther from them than the two closest picked rows lie from each other, it takes the place of
    the one of those two whose other neighbours are nearer. Each swap leaves the picked rows no closer together
    (the incoming row is farther from every kept one than the pair was), so the subset stays spread."""
    picked = np.asarray(picked).copy()
    if len(picked) < 2:
        return picked
    to_picked = _sq_dists(features, features[picked])  # (V, k)
    among = to_picked[picked]  # (k, k)
    np.fill_diagonal(among, np.inf)
    for _ in range(max(0, int(rounds))):
        outside = to_picked.min(axis=1)
        outside[picked] = -1.0
        u = int(np.argmax(outside))
        nearest = among.min(axis=1)
        a = int(np.argmin(nearest))
        if not outside[u] > nearest[a]:
            break
        b = int(np.argmin(among[a]))
        second = np.partition(among[[a, b]], 1, axis=1)[:, 1]  # each one's second-nearest picked view
        out = a if second[0] <= second[1] else b
        picked[out] = u
        to_picked[:, out] = np.sum((features - features[u]) ** 2, axis=1)
        among[out, :] = among[:, out] = to_picked[picked, out]
        among[out, out] = np.inf
    return picked


def _sq_dists(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) squared distances between the rows of `a` and `b`, a column at a time (a 10,000-view capture's
    distances to 256 views at once would hold 120 MB)."""
    return np.stack([np.sum((a - row) ** 2, axis=1) for row in b], axis=1) if len(b) else np.zeros((len(a), 0))


__all__ = ["MAX_SETUP_VIEWS", "spread_views"]
