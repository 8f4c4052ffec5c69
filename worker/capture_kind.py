"""Whether a capture holds measured or simulated histograms (the reconstruction and the baselines treat them apart:
a measured scene has a table in view and a background to estimate)."""

from __future__ import annotations

from spadscan.protocol.sensor_model import SensorModel


def is_measured(scene: dict, manifest: dict, sensor: SensorModel) -> bool:
    """Measured data? The scene's `real` flag when given; else not when the rig or its sensor is simulated; else
    whether the sensor model is a hardware one (it carries reference histograms)."""
    if "real" in scene:
        return bool(scene["real"])
    rig = manifest.get("rig") or {}
    if rig.get("kind") == "simulated":  # written by `spadscan simulate`
        return False
    if (rig.get("sensor") or {}).get("backend") == "sim":  # the daemon's simulated sensor
        return False
    return bool(sensor.has_reference)


__all__ = ["is_measured"]
