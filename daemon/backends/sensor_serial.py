"""Sensor backend `serial`: a TMF8820 behind the Arduino bridge, read with pyserial (`daemon/sensor/`)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import ClassVar

from spadscan.daemon.config_keys import key
from spadscan.protocol.errors import ConfigError

from spadscan.daemon.sensor.device_node import SERIAL_GROUP, node_problem

from .base import SensorBackend
from .tmf8820_preset import check_tmf8820_preset


@dataclass(frozen=True)
class SerialSensorSettings(SensorBackend):
    """[sensor] keys of backend 'serial'."""

    name: ClassVar[str] = "serial"

    port: str | None = key(None, "str")
    """Serial device of the bridge, e.g. /dev/ttyACM0 (required for 'serial')."""
    baud: int = key(1_000_000, "int", lo=1200, hi=12_000_000)
    """Baud rate of the bridge (the firmware prints at 1000000; some sketches at 115200)."""
    bridge_period_ms: int = key(230, "int", lo=1, hi=65535, unit="ms")
    """Measurement period the bridge's firmware sets, ms (the UW firmware's PERIOD: 230); frames count back two
    periods from the previous record to bound when their exposure began."""

    def checked(self, section, where, base):
        if self.port is None:
            raise ConfigError(f"{where} port is required for backend 'serial'")
        check_tmf8820_preset(section, where)
        return self

    def preflight(self, where: str) -> None:
        # Looking at the path opens nothing: a missing USB bridge would otherwise show only as a failed connect.
        if not os.path.exists(self.port):
            raise ConfigError(f"{where} port {self.port}: no such device (is the bridge plugged in? "
                              f"/dev/serial/by-id/ lists the connected ones)")
        problem = node_problem(self.port, SERIAL_GROUP, "tty")
        if problem is not None:
            raise ConfigError(f"{where} port {self.port}: {problem}")

    def build(self, sensor, model, arm, hand_eye, where):
        from spadscan.daemon.sensor import SerialSensor

        return SerialSensor(self.port, self.baud, model=model, period_ms=self.bridge_period_ms)

    def rig_record(self) -> dict:
        return {"port": self.port, "baud": self.baud}


BACKEND = SerialSensorSettings
