"""Views from one elevation: a capture whose views all look at the object from the same height above it.

Every view of one ring around a roundish object reads nearly the same histogram, and ranges taken from one elevation
do not fix the shape's profile in height: the fit explains every histogram with a wrong shape, and no check on the fit
can tell. A bottle 8 cm across and 20 cm tall seen by 64 views on one ring came out 17.3 mm at 20 degrees up (its top
out of every cone) and 14.8 mm aimed at its mid-height, 33.3 mm at 45 degrees up, each saying at most that it had
not converged or was in pieces (benchmarks/RESULTS.md, "a bad result says so"). The check needs the poses alone.
"""

from __future__ import annotations

import math

import numpy as np

ONE_RING_DEG = 5.0
"""Spread of the views' elevations (degrees, about the scene's centre) under which they are taken for one ring: a
second ring or a spiral spreads them over tens of degrees (the public dataset's real captures 36-83, its simulated
ones 0-86)."""


def view_elevations_deg(poses: np.ndarray, center, usable: np.ndarray | None = None) -> tuple[float, float, int]:
    """(lowest, highest elevation in degrees, views) of the sensors of the views (poses (V, 4, 4) sensor to world,
    metres) seen from `center` (3,) metres, 90 straight above it; views without any data (usable (V, Z) bool, None
    for all) and a sensor at the centre left out. (nan, nan, 0) when no view is left."""
    poses = np.asarray(poses, np.float64)
    if usable is not None:
        poses = poses[np.asarray(usable, bool).reshape(len(poses), -1).any(axis=1)]
    rel = poses[:, :3, 3] - np.asarray(center, np.float64)
    dist = np.linalg.norm(rel, axis=1)
    rel, dist = rel[dist > 0], dist[dist > 0]
    if not len(rel):
        return math.nan, math.nan, 0
    elevation = np.degrees(np.arcsin(np.clip(rel[:, 2] / dist, -1.0, 1.0)))
    return float(elevation.min()), float(elevation.max()), len(rel)


def one_ring_warning(low_deg: float, high_deg: float, views: int) -> str | None:
    """The line saying that the capture's `views` (at least 3) all stand within ONE_RING_DEG of one elevation
    (`low_deg` to `high_deg` about the scene's centre), or None."""
    if views < 3 or not (high_deg - low_deg < ONE_RING_DEG):
        return None
    return (f"the {views} views all stand {low_deg:.0f} to {high_deg:.0f} degrees up from the scene's centre, on one "
            f"ring: views from one elevation read nearly the same histogram and do not fix the shape's profile in "
            f"height, so the fit can explain them all with a wrong shape (a bottle seen so: 15-33 mm); scan with views "
            f"at two or more elevations (e.g. rings from 36 to 83 degrees, the public dataset's real captures' layout)")


__all__ = ["ONE_RING_DEG", "view_elevations_deg", "one_ring_warning"]
