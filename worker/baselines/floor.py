"""The floor a baseline assumes: the height below which the scene is empty.

A simulated scene stands on z = 0 (the convention of `spadscan simulate` and LCSPCData's simulated scenes). A measured
one stands on a table that every zone sees, wherever the rig put it: on LCSPCData's real pyramid it lies at
z = -0.155 m, and a floor at 0 threw away the lower two thirds of the object (reprojection 57 mm, against 11 mm
with the table's height). The baselines find the table as the `fast` reconstruction does
(`table_height.detect_height`), so that the two are compared on the same footing.
"""

from __future__ import annotations

import numpy as np

from spadscan.protocol.errors import ConfigError
from spadscan.protocol.plausibility import implausible
from spadscan.protocol.raycast import zone_rays

from ..capture_kind import is_measured
from ..pulse import pulse_kernel
from ..table_height import RAYS_PER_ZONE, detect_height, named_table

SIMULATED_FLOOR_Z = 0.0
"""Metres: the floor of a simulated scene, and of a measured one whose table cannot be found."""
NO_TABLE = "a scene without a table: z = 0"
NOT_FOUND = "no table found in the histograms; z = 0 assumed (--floor-z to set it)"
ASSUMED_FLOORS = (NO_TABLE, NOT_FOUND)
"""The sources of a floor that nothing in the capture showed: one that may cut an object reaching below z = 0
(run.floor_warning)."""


def scene_floor(data) -> tuple[float | None, str]:
    """(floor height in metres, or None for no floor; where it comes from) for a capture's data
    (protocol.capture_reader.CaptureData). The scene's `table` is read as the reconstruction reads it
    (recon/scene_data.py): a measured scene that says nothing stands on a table; `true`, or a horizontal table with
    `"fit": true`, is found in the histograms (a named height is the fallback); a named one without `fit` is used
    as given; none (`false`, or a simulated scene that says nothing) leaves the floor at z = 0."""
    scene = data.manifest.get("scene") or {}
    if not isinstance(scene, dict):
        scene = {}
    spec = scene.get("table", True if is_measured(scene, data.manifest, data.sensor) else None)
    if not spec:
        return SIMULATED_FLOOR_Z, NO_TABLE
    named = None
    if spec is not True:
        named = named_table(spec).height()
        if named is None:
            return None, "a tilted table: no horizontal floor"
        if not spec.get("fit", False):
            return named, "the table the capture names"
    height = measured_table_height(data)
    if height is not None:
        return height, "the table, found in the histograms"
    if named is not None:
        return named, "the table the capture names (not found in the histograms)"
    return SIMULATED_FLOOR_Z, NOT_FOUND


def check_given_floor(floor_z: float, poses: np.ndarray, sensor) -> None:
    """One-line ConfigError for a floor height (metres, --floor-z) that no view of the capture could have seen: above
    every sensor position (the scene would lie wholly under it), or farther below every sensor than the histograms
    reach (sensor.max_range_m). Both are what a height typed in millimetres gives (-156 for -0.156 m): the floor
    then either empties the scene or, far below it, quietly stops bounding the carving (a hull four times larger)."""
    heights = np.asarray(poses, np.float64)[:, 2, 3]
    top, bottom = float(heights.max()), float(heights.min())
    reach = float(sensor.max_range_m)
    if floor_z > top:
        raise ConfigError(f"--floor-z {floor_z:g} m lies above every sensor position (the highest at z = {top:.3f} m): "
                          f"the whole scene would be under the floor (metres, not millimetres?)")
    if floor_z < bottom - reach:
        raise ConfigError(f"--floor-z {floor_z:g} m lies {bottom - floor_z:.4g} m below the lowest sensor position "
                          f"(z = {bottom:.3f} m), beyond the histograms' range of {reach:.2f} m: no view could see "
                          f"such a floor (metres, not millimetres?)")


def measured_table_height(data) -> float | None:
    """Height (metres) of the horizontal table under a measured capture, or None when the histograms show none.

    Each histogram's background is its median bin (a TMF8820 histogram holds one or two returns in 128 bins)."""
    sensor = data.sensor
    if len(data.hists) == 0:
        return None
    # The frames of one pose summed, as the reconstruction sums them: the peak test sees all their counts.
    views = data.by_pose()
    # The histograms no sensor could have produced are left out, as the reconstruction leaves them out
    # (recon/scene_data.py): a corrupt bin would read as the farthest surface, the table, under it.
    broken = views.in_any_frame(implausible(data.hists, *data.count_bounds()))
    counts, cycles = np.where(broken[..., None], 0.0, views.counts), views.frames * float(sensor.cycles)
    poses = np.asarray(data.poses, np.float64)[views.first]
    background = np.median(counts, axis=-1) / cycles[:, None]
    reference = None if data.reference is None else np.asarray(data.reference, np.float64).mean(axis=0)
    kernel, origin, _ = pulse_kernel(sensor, reference)
    rays = zone_rays(sensor.zones, RAYS_PER_ZONE, 0)
    return detect_height(counts, cycles, background, poses, rays.directions,
                         rays.weights, sensor, np.asarray(kernel, float), origin, ignore_bins=sensor.ignore_bins)


__all__ = ["SIMULATED_FLOOR_Z", "ASSUMED_FLOORS", "NO_TABLE", "NOT_FOUND", "scene_floor", "measured_table_height",
           "check_given_floor"]
