"""The frames of one pose read as one view by carving and the first-return search.

A capture may hold several frames per pose (`frames_per_pose`); the reconstruction sums them into one histogram per
zone (their cycles add up). Carving and the first-return search read a histogram with the sensor's `cycles` (pile-up
is undone over them, the background is a rate per cycle): a view of k frames is a histogram of k x cycles. Counted
frame by frame instead, space that one pose alone saw passes as seen by k views.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from spadscan.protocol.sensor_model import SensorModel


def summed_views(counts: np.ndarray, frames: np.ndarray, sensor: SensorModel) -> tuple[np.ndarray, SensorModel]:
    """(counts, sensor) that carving reads as one histogram per view: `counts` (V, zones, bins), each view's frames
    summed, `frames` (V,) frames per view. The sensor's cycles become the most frames times its cycles; a view of
    fewer frames (a pose cut short) has its counts scaled up to as many (its noise is then slightly understated)."""
    frames = np.asarray(frames, dtype=np.float64)
    if frames.shape != counts.shape[:1] or not np.all(frames >= 1):
        raise ValueError(f"frames per view {frames.shape} must be >= 1 for each of the {len(counts)} views")
    most = int(round(float(frames.max()))) if len(frames) else 1
    if most == 1:
        return counts, sensor
    scaled = np.asarray(counts, dtype=np.float64) * (most / frames)[:, None, None]
    return scaled, dataclasses.replace(sensor, cycles=int(sensor.cycles) * most)


def summed_by_cycles(counts: np.ndarray, cycles: np.ndarray, sensor: SensorModel) -> tuple[np.ndarray, SensorModel]:
    """`summed_views` of views told by their laser cycles: `counts` (V, zones, bins) each view's frames summed,
    `cycles` (V,) its cycles (its frames x the sensor's `cycles`, a frame's), as a loaded scene holds them."""
    frames = np.round(np.asarray(cycles, np.float64) / float(sensor.cycles))
    return summed_views(counts, frames, sensor)


__all__ = ["summed_views", "summed_by_cycles"]
