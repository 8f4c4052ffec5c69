"""What every backend module provides: a frozen dataclass of the backend's own keys (read from the same [arm] or
[sensor] table as the common keys), whose methods are the backend's checks, constructor and rig record.

    @dataclass(frozen=True)
    class SerialSensorSettings(SensorBackend):
        name: ClassVar[str] = "serial"
        port: str | None = key(None, "str")
        ...
    BACKEND = SerialSensorSettings

The config reader finds the class by the table's `backend` name once (`backends.ARM_BACKENDS`, `SENSOR_BACKENDS`)
and keeps an instance in the section (`ArmConfig.device`, `SensorConfig.device`); everything afterwards calls its
methods. Device classes are imported inside `build`, so that choosing one backend never imports another's libraries
(a sim rig never loads ur_rtde, a serial one never smbus2).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from spadscan.protocol.sensor_model import SensorModel

if TYPE_CHECKING:
    from spadscan.daemon.config import ArmConfig, SensorConfig
    from spadscan.daemon.devices import Arm, Sensor


class BackendSettings:
    """Base of a backend's settings dataclass; `name` is the value of `backend` that chooses it."""

    name: ClassVar[str] = ""

    def checked(self, section, where: str, base: Path | None):
        """Cross-key checks at load time (required keys, files that must exist), raising a one-line ConfigError that
        starts with `where`; returns the settings to keep (relative paths resolved against `base`, the config
        file's folder). `section` is the whole ArmConfig or SensorConfig, for checks that need the common keys."""
        return self

    def preflight(self, where: str) -> None:
        """What start-up and `spadscan daemon --check` verify beyond the file, touching no device: a device node is
        present, a firmware image parses. One-line ConfigError starting with `where`."""

    def rig_record(self) -> dict:
        """This backend's part of the rig record stored in every capture's manifest (merged into its section)."""
        return {}


class ArmBackend(BackendSettings):
    """Settings of an arm backend."""

    unattended_resume_ok: ClassVar[bool] = True
    """Whether `auto_resume = true` may move this arm without a second, explicit confirmation (a simulated arm)."""

    def build(self, arm: "ArmConfig") -> "Arm":
        """The arm, not yet connected. `arm` holds the common keys (speed, acceleration, limits)."""
        raise NotImplementedError

    def confirms_unattended_resume(self) -> bool:
        """Whether these settings confirm that `auto_resume = true` may move the arm unattended."""
        return self.unattended_resume_ok


class SensorBackend(BackendSettings):
    """Settings of a sensor backend."""

    renders_at_arm_pose: ClassVar[bool] = False
    """The sensor needs the arm's live pose (a simulated sensor renders the scene there)."""
    renders_with_model: ClassVar[bool] = False
    """The sensor's histograms are made with its sensor model (a simulated sensor renders with it), so a scan goes on
    only with the model it was planned with. A real sensor's are not: its driver checks only the zone and bin counts
    against the model, and a capture is read with the one model it records."""
    model_keys: ClassVar[dict[str, str]] = {}
    """Sensor model fields this backend's keys set (`model`), each with its key: recorded in the rig record, so that a
    resumed scan tells a changed key from a preset an update refitted."""

    def model(self, preset: SensorModel, where: str) -> SensorModel:
        """The sensor model stored with every capture: the preset, with any of this backend's overrides folded in."""
        return preset

    @classmethod
    def preset_value(cls, field: str, value, rig: dict):
        """The preset's own value of sensor model field `field`, from the model's `value` and the keys this backend
        recorded in the capture's rig record (`rig`, its sensor part): `model` undone. None where a key replaced it
        (the preset's value cannot be told). No key of this backend's sets a field: the value is the preset's."""
        return value

    def build(self, sensor: "SensorConfig", model: SensorModel, arm: "Arm", hand_eye: np.ndarray,
              where: str) -> "Sensor":
        """The sensor, not yet connected; `arm` is the rig's arm (for a sensor that renders at its pose)."""
        raise NotImplementedError

    def scene_record(self) -> dict:
        """The scene record stored in every capture (a simulated sensor's mesh, so the worker finds the ground
        truth); empty for a real sensor."""
        return {}
