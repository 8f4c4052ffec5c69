"""Sensor backend `i2c`: a TMF8820 on an I2C bus through smbus2, its firmware downloaded at boot (`daemon/sensor/`)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from spadscan.daemon.config_keys import key
from spadscan.protocol.errors import ConfigError, DeviceError

from spadscan.daemon.sensor.device_node import I2C_GROUP, node_problem

from .base import SensorBackend
from .tmf8820_preset import check_tmf8820_preset


@dataclass(frozen=True)
class I2CSensorSettings(SensorBackend):
    """[sensor] keys of backend 'i2c'."""

    name: ClassVar[str] = "i2c"

    bus: int | None = key(None, "int", lo=0, hi=255)
    """I2C bus number, /dev/i2c-N (required for 'i2c')."""
    address: int = key(0x41, "int", lo=0x08, hi=0x77)
    """7-bit I2C address of the sensor (0x41)."""
    firmware: Path | None = key(None, "path")
    """Path to your copy of the ams application image (.hex) downloaded at boot (required for 'i2c'; never shipped)."""

    def checked(self, section, where, base):
        for name in ("bus", "firmware"):
            if getattr(self, name) is None:
                raise ConfigError(f"{where} {name} is required for backend 'i2c'")
        check_tmf8820_preset(section, where)
        if self.firmware.is_dir():
            raise ConfigError(f"{where} firmware {self.firmware} is a folder, not a file (point it at the ams "
                              f"application image inside it, e.g. its .hex file)")
        if not self.firmware.is_file():
            raise ConfigError(f"{where} firmware {self.firmware}: no such file (point it at your copy of the ams "
                              f"application image)")
        return self

    def preflight(self, where: str) -> None:
        from spadscan.daemon.sensor.firmware import load_firmware

        try:
            load_firmware(self.firmware)
        except DeviceError as exc:
            raise ConfigError(f"{where} firmware: {exc}") from None
        if not os.path.exists(self.node):
            raise ConfigError(f"{where} bus {self.bus}: {self.node}: no such device (is I2C enabled?)")
        problem = node_problem(self.node, I2C_GROUP, "i2c-dev")
        if problem is not None:
            raise ConfigError(f"{where} bus {self.bus}: {self.node}: {problem}")

    @property
    def node(self) -> str:
        """The bus's device node."""
        return f"/dev/i2c-{self.bus}"

    def build(self, sensor, model, arm, hand_eye, where):
        from spadscan.daemon.sensor import I2CSensor

        return I2CSensor(self.bus, self.address, self.firmware, model=model)

    def rig_record(self) -> dict:
        return {"bus": self.bus, "address": self.address}


BACKEND = I2CSensorSettings
