"""The floor a baseline assumes: the height below which the scene is empty.

A simulated scene stands on z = 0 (the convention of `spadscan simulate` and LCSPCData's simulated scenes). A measured
one stands on a table that every zone sees, wherever the rig put it: on LCSPCData's real pyramid it lies at
z = -0.155 m, and a floor at 0 threw away the lower two thirds of the object (reprojection 57 mm, against 11 mm
with the table's height). The baselines find the table as the `fast` reconstruction does
(`table_height.detect_height`), so that the two are compared on the same footing.
"""

from __future__ import annotations

import numpy as np

SIMULATED_FLOOR_Z = 0.0
"""Metres: the floor of a simulated scene, and of a measured one whose table cannot be found."""

RAYS_PER_ZONE = 48
"""Rays per zone for the table's predicted peaks: enough to place a peak to a bin (as the reconstruction uses)."""


def scene_floor(data) -> tuple[float, str]:
    """(floor height in metres, where it comes from) for a capture's data (protocol.capture_reader.CaptureData)."""
    from ..capture_kind import is_measured

    scene = data.manifest.get("scene") or {}
    spec = scene.get("table") if isinstance(scene, dict) else None
    if isinstance(spec, dict):
        named = _named_height(spec)
        if named is not None:
            return named, "the table the capture names"
    if not isinstance(scene, dict) or spec is False or not is_measured(scene, data.manifest, data.sensor):
        return SIMULATED_FLOOR_Z, "a simulated scene's floor"
    height = measured_table_height(data)
    if height is None:
        return SIMULATED_FLOOR_Z, "no table found in the histograms; z = 0 assumed (--floor-z to set it)"
    return height, "the table, found in the histograms"


def _named_height(spec: dict) -> float | None:
    """Height (metres) of a horizontal table given as {"z": h} or {"normal": n, "offset": d}; None otherwise."""
    try:
        if "z" in spec:
            return float(spec["z"])
        normal = np.asarray(spec.get("normal", (0, 0, 1)), float)
        norm = float(np.linalg.norm(normal))
        if normal.shape == (3,) and norm > 0 and abs(normal[2]) / norm > 0.99 and "offset" in spec:
            return float(spec["offset"]) / float(normal[2])
    except (TypeError, ValueError):
        pass
    return None


def measured_table_height(data) -> float | None:
    """Height (metres) of the horizontal table under a measured capture, or None when the histograms show none.

    Each histogram's background is its median bin (a TMF8820 histogram holds one or two returns in 128 bins)."""
    from spadscan.protocol.raycast import zone_rays

    from ..recon.pulse import pulse_kernel
    from ..table_height import detect_height

    sensor = data.sensor
    counts = np.asarray(data.hists, np.float64)
    if len(counts) == 0:
        return None
    cycles = np.full(len(counts), float(sensor.cycles))
    background = np.median(counts, axis=-1) / cycles[:, None]
    reference = None if data.reference is None else np.asarray(data.reference, np.float64).mean(axis=0)
    kernel, origin, _ = pulse_kernel(sensor, reference)
    rays = zone_rays(sensor.zones, RAYS_PER_ZONE, 0)
    return detect_height(counts, cycles, background, np.asarray(data.poses, np.float64), rays.directions,
                         rays.weights, sensor, np.asarray(kernel, float), origin, ignore_bins=sensor.ignore_bins)


__all__ = ["SIMULATED_FLOOR_Z", "scene_floor", "measured_table_height"]
