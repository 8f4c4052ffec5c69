"""Views from one elevation, or from above only: a capture whose views all look at the object from the same height
above it, or all from high above it.

Every view of one ring around a roundish object reads nearly the same histogram, and ranges taken from one elevation
do not fix the shape's profile in height: the fit explains every histogram with a wrong shape, and no check on the fit
can tell. A bottle 8 cm across and 20 cm tall seen by 64 views on one ring came out 17.3 mm at 20 degrees up (its top
out of every cone) and 14.8 mm aimed at its mid-height, 33.3 mm at 45 degrees up, each saying at most that it had
not converged or was in pieces (benchmarks/RESULTS.md, "a bad result says so"). Views that all look down steeply see
upright sides only at a grazing angle, their returns merged in time with the top's: a block's sides came out flared by
up to 25 mm at the base, the fit within photon noise of every histogram, and its coverage counting the flared walls,
which face up, as seen. The checks need the poses alone.
"""

from __future__ import annotations

import math

import numpy as np

ONE_RING_DEG = 5.0
"""Spread of the views' elevations (degrees, about the scene's centre) under which they are taken for one ring: a
second ring or a spiral spreads them over tens of degrees (the public dataset's real captures 7-80, scanned on rings
from 36 to 83 about a target above the table; its simulated ones -9 to 86)."""

ABOVE_ONLY_DEG = 45.0
"""Lowest view elevation (degrees, about the scene's centre) from which on a capture is taken to look down from above
only. Measured about the centre (which stands at the object's mid-height, so lower than a schedule's band about its
target): a 16 cm block seen from 48-88 degrees came out 7-10 mm at three runs, every check quiet; an L-bracket from 58
up 8.1 mm; the block on a table with the tmf8820 from 50 up 3.9 mm; the block from 37 up 2.3 mm and from 28 up 1.4
(benchmarks/RESULTS.md, "a bad result says so"). The public dataset's captures reach 10 degrees or lower (the real
pyramid 10, its `_random` twin 7, the simulated ones below 0)."""


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


def above_only_warning(low_deg: float, high_deg: float, views: int) -> str | None:
    """The line saying that the capture's `views` (at least 3) all look down from ABOVE_ONLY_DEG or more (`low_deg`
    to `high_deg` about the scene's centre), or None."""
    if views < 3 or not low_deg >= ABOVE_ONLY_DEG:
        return None
    return (f"the {views} views all look down from {low_deg:.0f} to {high_deg:.0f} degrees up from the scene's "
            f"centre: upright sides are seen only at a grazing angle, their returns merged with the top's, and the "
            f"fit can flare them out while explaining every histogram (a 16 cm block seen from 48 degrees up: 7-10 "
            f"mm); if the object has sides, scan with views from lower down too (the public dataset's real captures "
            f"reach 10 degrees about the object's centre)")


def one_ring_warning(low_deg: float, high_deg: float, views: int) -> str | None:
    """The line saying that the capture's `views` (at least 3) all stand within ONE_RING_DEG of one elevation
    (`low_deg` to `high_deg` about the scene's centre), or None."""
    if views < 3 or not (high_deg - low_deg < ONE_RING_DEG):
        return None
    return (f"the {views} views all stand {low_deg:.0f} to {high_deg:.0f} degrees up from the scene's centre, on one "
            f"ring: views from one elevation read nearly the same histogram and do not fix the shape's profile in "
            f"height, so the fit can explain them all with a wrong shape (a bottle seen so: 15-33 mm); scan with views "
            f"at two or more elevations (e.g. rings from 36 to 83 degrees, the public dataset's real captures' layout)")


__all__ = ["ONE_RING_DEG", "ABOVE_ONLY_DEG", "view_elevations_deg", "one_ring_warning", "above_only_warning"]
