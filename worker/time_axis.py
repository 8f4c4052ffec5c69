"""Whether a capture's time axis puts its returns where the scene can be: a check before the fit.

A sensor record whose time axis is wrong (its bin width or zero_bin) puts every return at the wrong range; carving
and the floor would then blame the scene's bound ("space carving removed everything ... check scene.radius") or the
floor. The strong returns are compared with spheres found without them (the scene record's, and the one around the
point the views look at), and the capture is refused when most lie where no surface of the scene can be.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spadscan.protocol.errors import CaptureError

from .carving.bounds import RADIUS_FRACTION_MAX, given_sphere
from .carving.returns import matched_filter_z
from .carving.views import summed_by_cycles


NEAR_RANGE_M = 0.01
"""Range (metres) under which piled-up photons say a surface touches the sensor: no return this near is told from
the pulse's own start (the scene's first returns count from here on: recon/scene_data.py)."""
STRONG_Z = 10.0
"""A histogram's strongest peak is a strong return at this many standard deviations of its matched-filtered
background (twice the detection threshold): the time-axis check reads only those, which noise never makes."""
IN_SCENE_SHARE = 0.5
"""The time axis is refused when fewer than this share of the strong returns lie where the scene can be: most of
them elsewhere. Every good capture measured has all of them there (docs/end_of_run.md), a wrong time axis none."""
RANGE_FACTOR = 2.0
"""A strong return lies where the scene can be when its range is within this factor of a view's distances to the
near and far side of the scene's sphere (and RANGE_SLACK_BINS more): the sphere is a bound, not a measurement (the
point the views look at is not the object's centre, a table lies beyond the object), and the check is for a time
axis wrong by far more (a bin width of 1 m: returns 70 times as far; a zero_bin hundreds of bins off)."""
RANGE_SLACK_BINS = 3.0
"""Bins of slack on either side: a strong peak places its surface to a bin or two."""
AIM_COS = 0.5
"""A view enters the check when a sphere's centre lies within 60 degrees of its boresight (or it is inside the
sphere): a view that aims elsewhere says nothing of where the scene's surfaces lie."""
BORESIGHT_SPREAD = 0.1
"""The least spread of the views' boresights (the smallest eigenvalue of their mean projection I - a a^T) at which
the point they look at is taken as known: two views 37 degrees apart, one ring of views up to 72 degrees of
elevation. Whole captures have 0.27-0.67; two or three neighbouring views of a capture whose views are turned at
random (LCSPCData's `_random`) have under 0.03, and their boresights cross wherever the turns put them (a few cm
from the sensors)."""

MISS_RATIO = 0.25
"""The point the views look at is known when most views' boresights pass it within this share of their distance
to it (14 degrees): views turned at random by 10 degrees (LCSPCData's `_random`) do; views aimed at two objects
half a metre apart miss the point between them by more than half their distance."""


@dataclass
class ReturnPlaces:
    """Where a capture's strong returns lie against the scene's sphere (`return_places`)."""

    ranges_m: np.ndarray
    """(n,) range of each strong return of the views that aim at the scene, metres from its sensor."""
    inside: np.ndarray
    """(n,) bool: the return lies where the scene can be."""
    near_m: float
    """The nearest any of those views is to the near side of the sphere, metres."""
    far_m: float
    """The farthest any of them is from its far side, metres."""

    @property
    def share(self) -> float:
        """The share of the strong returns that lie where the scene can be."""
        return float(np.mean(self.inside))


def check_time_axis(capture, record: dict, poses: np.ndarray, counts: np.ndarray, sensor,
                    usable: np.ndarray | None = None) -> None:
    """Refuse (one CaptureError line) a capture whose strong returns mostly lie where no surface of the scene can be
    (`return_places`, fewer than IN_SCENE_SHARE of them where it can): a wrong time axis in the sensor record (its
    bin width or zero_bin), which carving and the floor would otherwise blame on the scene's bound (a bin width of
    1 m: "space carving removed everything ... check scene.radius"; a zero_bin of 1000: the floor's advice).
    `record`: the capture's scene record; `poses` (V, 4, 4), `counts` (V, zones, bins) one view per pose, its frames
    summed, `sensor` the model of such a view (`carving.views.summed_views`); `usable` (V, zones): the histograms
    that hold data."""
    given_sphere(record, Path(capture) / "scan.json")  # a malformed centre or radius said as such, by the file
    places = return_places(record, poses, counts, sensor, usable)
    if places is None or places.share >= IN_SCENE_SHARE:
        return
    out = places.ranges_m[~places.inside]
    before = " (negative: before the time axis's zero)" if out.min() < 0 else ""
    if out.max() < NEAR_RANGE_M:
        # Every such return at the start of the range: photons piled up from a surface touching the sensor (their
        # peak can fall bins before the zero) look just as a zero_bin set too late does; the first is the likelier.
        raise CaptureError(f"{capture}: {out.size} of {places.inside.size} strong returns lie {_metres(out.min())} "
                           f"to {_metres(out.max())} m from the sensor{before}, at the start of its range, but the "
                           f"scene's sphere is {_metres(places.near_m)} to {_metres(places.far_m)} m from the views: "
                           f"the photons pile up in the first bins, as from a surface touching the sensor (move the "
                           f"sensor back from it), or the sensor record's sensor.zero_bin ({sensor.zero_bin:g}) in "
                           f"its scan.json is wrong")
    raise CaptureError(f"{capture}: {out.size} of {places.inside.size} strong returns lie {_metres(out.min())} to "
                       f"{_metres(out.max())} m from the sensor{before}, but the scene's sphere is "
                       f"{_metres(places.near_m)} to {_metres(places.far_m)} m from the views: no surface of the "
                       f"scene can be there; check the time axis of the sensor record in its scan.json: "
                       f"sensor.bin_width_m ({sensor.bin_width_m:g} m a bin) and sensor.zero_bin "
                       f"({sensor.zero_bin:g})")


def scene_views(scene) -> tuple:
    """A loaded scene (`recon.scene_data.SceneData`) as `check_time_axis` reads it after the capture's name: (scene
    record, poses, counts, sensor, usable), numpy, one view per pose."""
    counts, sensor = summed_by_cycles(scene.counts.double().cpu().numpy(), scene.cycles.double().cpu().numpy(),
                                      scene.sensor)
    usable = None if scene.usable is None else scene.usable.cpu().numpy()
    return scene.scene, scene.poses.detach().double().cpu().numpy(), counts, sensor, usable


def return_places(record: dict, poses: np.ndarray, counts: np.ndarray, sensor,
                  usable: np.ndarray | None = None) -> ReturnPlaces | None:
    """Where the strong returns (`STRONG_Z`) of the views that aim at the scene lie: where the scene can be when
    within `RANGE_FACTOR` of their view's distance to the near and far side of the scene's sphere. The sphere is the
    scene record's, and that around the point the views look at, as large as the scene's bound can be
    (`carving.bounds.RADIUS_FRACTION_MAX` of the nearest view's distance): both found without the returns, which a
    wrong time axis puts in the wrong place (the scene's own sphere is found from them). None where there is no
    such sphere (no centre given, views that look at no common point) or no strong return. Arguments as
    `check_time_axis`'s."""
    near, far = _scene_ranges(record, np.asarray(poses, dtype=np.float64))
    if near is None:
        return None
    ranges, strong = _strong_returns(counts, sensor, usable)
    strong &= np.isfinite(near)[:, None]
    if not strong.any():
        return None
    slack = RANGE_SLACK_BINS * sensor.bin_width_m
    inside = (ranges >= near[:, None] / RANGE_FACTOR - slack) & (ranges <= far[:, None] * RANGE_FACTOR + slack)
    seen = strong.any(axis=1)
    return ReturnPlaces(ranges[strong], inside[strong], float(near[seen].min()), float(far[seen].max()))


def _metres(value: float) -> str:
    return f"{value:.2f}"


def _strong_returns(counts: np.ndarray, sensor, usable) -> tuple[np.ndarray, np.ndarray]:
    """(range (V, Z) metres of each histogram's strongest matched-filtered peak, whether it is strong (`STRONG_Z`)),
    histograms without data left out."""
    z = matched_filter_z(counts, sensor, "matched", usable)
    peak = np.argmax(z, axis=-1)
    strong = np.take_along_axis(z, peak[..., None], -1)[..., 0] >= STRONG_Z
    return sensor.range_of_bin(peak + 0.5), strong


def _scene_ranges(record: dict, poses: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(near, far) (V,) metres: each view's distance to the near and far side of the spheres the scene can lie in
    (`check_time_axis`) that it aims at (`AIM_COS`), the nearest and farthest over them; NaN for a view that aims at
    none. (None, None) where there is no sphere."""
    origins, axes = poses[:, :3, 3], poses[:, :3, 2]
    spheres = []
    centre, given = given_sphere(record, "scan.json")
    if centre is not None:
        reach = given if given is not None else RADIUS_FRACTION_MAX * _nearest(origins, centre)
        spheres.append((centre, reach))
    looked_at = _looked_at_point(origins, axes)
    if looked_at is not None:  # at least as large as a radius the record gives: the object's size
        reach = RADIUS_FRACTION_MAX * _nearest(origins, looked_at)
        spheres.append((looked_at, max(reach, given) if given is not None else reach))
    if not spheres:
        return None, None
    near = np.full(len(poses), np.inf)
    far = np.full(len(poses), -np.inf)
    for centre, reach in spheres:
        to = centre - origins
        dist = np.linalg.norm(to, axis=1)
        aims = (np.einsum("ij,ij->i", to, axes) >= AIM_COS * dist) | (dist <= reach)
        near = np.where(aims, np.minimum(near, np.maximum(dist - reach, 0.0)), near)
        far = np.where(aims, np.maximum(far, dist + reach), far)
    none = ~np.isfinite(far)
    return np.where(none, np.nan, near), np.where(none, np.nan, far)


def _nearest(origins: np.ndarray, point: np.ndarray) -> float:
    return float(np.linalg.norm(origins - point, axis=1).min())


def _looked_at_point(origins: np.ndarray, axes: np.ndarray) -> np.ndarray | None:
    """The point nearest to every view's boresight (least squares), or None where the boresights spread too little
    to meet anywhere known (`BORESIGHT_SPREAD`: a single view, views looking the same way), or where they do not
    meet there (`MISS_RATIO`: views aimed at two objects have a least-squares point between them, nearer than
    either, and their returns would lie beyond its sphere)."""
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    a, b = proj.mean(0), np.einsum("nij,nj->i", proj, origins) / len(origins)
    if not np.linalg.eigvalsh(a)[0] >= BORESIGHT_SPREAD:
        return None
    point = np.linalg.solve(a, b)
    to = point - origins
    miss = np.linalg.norm(np.einsum("nij,nj->ni", proj, to), axis=1)
    along = np.maximum(np.einsum("ij,ij->i", to, axes), 1e-9)
    return point if np.median(miss / along) <= MISS_RATIO else None


__all__ = ["STRONG_Z", "IN_SCENE_SHARE", "ReturnPlaces", "check_time_axis", "return_places", "scene_views"]
