"""Whether a capture holds measured or simulated histograms (the reconstruction and the baselines treat them apart:
a measured scene has a table in view and a background to estimate)."""

from __future__ import annotations

from spadscan.protocol.capture_format import drawn_by_simulator
from spadscan.protocol.capture_reader import scene_real
from spadscan.protocol.sensor_model import SensorModel


def is_measured(scene: dict, manifest: dict, sensor: SensorModel) -> bool:
    """Measured data? The scene's `real` flag when given; else not when the rig or its sensor is simulated; else
    whether the sensor model is a hardware one (it carries reference histograms)."""
    real = scene_real(scene, "manifest")  # the reader's own check: one read elsewhere is held to it too
    if real is not None:
        return real
    if drawn_by_simulator(manifest):  # written by `spadscan simulate`, or by the daemon's simulated sensor
        return False
    return bool(sensor.has_reference)


__all__ = ["is_measured"]
