"""Views from one elevation, from above only, from low down only, or from far away: a capture whose views all look at
the object from the same height above it, all from high above it, all from near its base's height, or from so far
that each zone sees a patch wider than the object's parts (or several times the whole object).

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

LOW_ONLY_DEG = 45.0
"""Highest view elevation (degrees, about the scene's centre) up to which a capture is taken to look from low down
only: the object's top is then seen at a grazing angle alone, its returns spread over many bins and merged with the
sides', and the fit can put it centimetres off while explaining every histogram (LOW_ONLY_EVIDENCE). Measured about
the centre: a flat plate (20 cm across, 1 cm thick, 64 views) came out 1.15 mm from views up to 83 degrees, 4.12 up to
42 (quiet), 9.43 up to 32, and left no surface up to 23; a teddy (128 views) 10.6 mm up to 23. The mirror of
ABOVE_ONLY_DEG; the public dataset's captures reach 80 degrees and more (its simulated ones 86, its real ones 80
about the target)."""
LOW_ONLY_EVIDENCE = "a flat plate seen from 42 degrees up at most: 4.1 mm, against 1.2 from up to 83"
"""What captures from low down came out at, said in the warning."""

FAR_PATCH_M = 0.27
"""Width (metres) of the patch one zone sees at the views' median return range over which a capture is said to be
taken from far away: each histogram then sums the returns of a patch wider than most objects' parts, and the fit
explains every one of them with a blurred shape. Set on the tuning split's cup and lamp scanned from farther: the
lamp from 0.7 m (a 31 cm patch) came out 4.72 mm against 1.68 from 0.5 m, the cup 1.85 and 1.67 from 0.7 and 0.6 m
(33 and 27 cm) against 1.50; every benchmark capture sees 3.0-25 cm (lcspc-sim from 0.5 m, the TMF8820's 9 zones from
0.13-0.45 m; benchmarks/RESULTS.md, "The hull's piece vote ...; views from far away")."""


SMALL_PATCH_RATIO = 1.8
"""How many times the object's size (the mesh's largest extent) the patch one zone sees at the views' median return
range may be before a capture is said to see a small object: each histogram then holds the whole object in one
blurred return, and the fit trades its size against its brightness (SMALL_EVIDENCE). Every benchmark capture's zone
sees 0.1-1.6 times its object (the mug 1.5 and the lcspc-sim pyramid 1.5, 1.40 and 0.82 mm; the cup from 0.6 m 1.7,
1.67 mm); a 12 cm ball's 2.0 times (2.44 mm), an 8 cm one's 3.0."""
SMALL_EVIDENCE = ("white balls of 3, 5, 8 and 12 cm seen by 64 views from 0.5 m came out 3.4, 3.1, 2.8 and 2.5 mm, "
                  "their meshes 4.8, 6.4, 8.4 and 12.3 cm across, where a 20 cm sphere comes out 0.7")
"""What small objects came out at, said in the warning."""


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


def low_only_warning(low_deg: float, high_deg: float, views: int) -> str | None:
    """The line saying that the capture's `views` (at least 3) all stand LOW_ONLY_DEG or less above the scene's centre
    (`low_deg` to `high_deg`), or None."""
    if views < 3 or not high_deg <= LOW_ONLY_DEG:
        return None
    return (f"the {views} views all stand {low_deg:.0f} to {high_deg:.0f} degrees up from the scene's centre, none "
            f"higher: the object's top is seen only at a grazing angle, its returns spread over many bins and merged "
            f"with the sides', and the fit can put it centimetres off while explaining every histogram "
            f"({LOW_ONLY_EVIDENCE}); if the object has a top, scan with views from higher up too (the public "
            f"dataset's captures reach 80 degrees or more)")


def one_ring_warning(low_deg: float, high_deg: float, views: int) -> str | None:
    """The line saying that the capture's `views` (at least 3) all stand within ONE_RING_DEG of one elevation
    (`low_deg` to `high_deg` about the scene's centre), or None."""
    if views < 3 or not (high_deg - low_deg < ONE_RING_DEG):
        return None
    return (f"the {views} views all stand {low_deg:.0f} to {high_deg:.0f} degrees up from the scene's centre, on one "
            f"ring: views from one elevation read nearly the same histogram and do not fix the shape's profile in "
            f"height, so the fit can explain them all with a wrong shape (a bottle seen so: 15-33 mm); scan with views "
            f"at two or more elevations (e.g. rings from 36 to 83 degrees, the public dataset's real captures' layout)")


def zone_patch_m(sensor, range_m: float) -> float:
    """Width (metres) of the patch one zone of `sensor` sees at `range_m` metres: the diameter of the cone of the
    zones' mean solid angle."""
    solid = float(np.mean([zone.solid_angle_sr() for zone in sensor.zones]))
    half = math.acos(max(-1.0, 1.0 - solid / (2.0 * math.pi)))
    return 2.0 * range_m * math.tan(min(half, math.radians(89.0)))


def far_views_warning(sensor, ranges_m: np.ndarray) -> str | None:
    """The line saying that the views' returns (`ranges_m`, metres, one per histogram with a return) lie so far that
    one zone sees a patch wider than FAR_PATCH_M at their median, or None (None too for fewer than 3 returns)."""
    ranges_m = np.asarray(ranges_m, np.float64)
    if len(ranges_m) < 3:
        return None
    median = float(np.median(ranges_m))
    patch = zone_patch_m(sensor, median)
    if not patch > FAR_PATCH_M:
        return None
    closer = _range_for_patch(sensor, FAR_PATCH_M)
    return (f"the views' returns lie {median:.2f} m away (median), where each zone of the {sensor.name} sees a patch "
            f"{100 * patch:.0f} cm across: each histogram sums a patch wider than most of an object's parts, and the "
            f"fit can explain every one with a blurred shape; scan closer (within {closer:.2f} m, where a zone's patch "
            f"is {100 * FAR_PATCH_M:.0f} cm or less)")


def small_object_warning(sensor, ranges_m: np.ndarray, extent_m: float) -> str | None:
    """The line saying that one zone sees a patch over SMALL_PATCH_RATIO times the object's size (`extent_m`, metres:
    the mesh's largest extent) at the views' median return range (`ranges_m`, one per histogram with a return), or
    None (None too for fewer than 3 returns or a mesh of no extent)."""
    ranges_m = np.asarray(ranges_m, np.float64)
    if len(ranges_m) < 3 or not extent_m > 0:
        return None
    median = float(np.median(ranges_m))
    patch = zone_patch_m(sensor, median)
    if not patch > SMALL_PATCH_RATIO * extent_m:
        return None
    closer = _range_for_patch(sensor, SMALL_PATCH_RATIO * extent_m)
    return (f"the object is small against the sensor's view: the mesh is {100 * extent_m:.1f} cm across, where each "
            f"zone of the {sensor.name} sees a patch {100 * patch:.0f} cm across at the views' returns ({median:.2f} "
            f"m away, median), so each histogram holds the whole object in one blurred return, its size, shape and "
            f"brightness traded against each other ({SMALL_EVIDENCE}); scan closer (within {closer:.2f} m, where a "
            f"zone's patch is {SMALL_PATCH_RATIO:g} times its size)")


def _range_for_patch(sensor, patch_m: float) -> float:
    """The range (metres) at which one zone of `sensor` sees a patch `patch_m` metres across."""
    return patch_m / zone_patch_m(sensor, 1.0)


__all__ = ["ONE_RING_DEG", "ABOVE_ONLY_DEG", "LOW_ONLY_DEG", "FAR_PATCH_M", "SMALL_PATCH_RATIO",
           "view_elevations_deg", "one_ring_warning", "above_only_warning", "low_only_warning", "zone_patch_m",
           "far_views_warning", "small_object_warning"]
