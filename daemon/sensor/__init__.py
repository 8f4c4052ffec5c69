"""Sensor backends: the TMF8820 over an Arduino serial bridge or the I2C bus, and a simulated sensor.

    SerialSensor(port, baud=1_000_000, *, model=None, frame_timeout_s=2.0, ...)     pyserial, `#Raw`/`#Obj` lines
    I2CSensor(bus, address=0x41, firmware=None, *, model=None, period_ms=..., ...)    smbus2, firmware download
    SimSensor(model, mesh, pose_provider, *, settings=None, seed=0, frame_time_s=0)   the simulator at the pose

The two TMF8820 backends share one device class (`tmf8820.TMF8820`) over a byte-level transport
(`transport.Transport`); their twins are `sim_bridge.SimBridge` (a pty) and `sim_i2c.SimTMF8820Bus` (an SMBus fake).
Names are imported lazily so that choosing one backend does not import the others' libraries.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "TMF8820": ".tmf8820",
    "SerialSensor": ".serial_bridge",
    "I2CSensor": ".i2c_bus",
    "SimSensor": ".sim",
    "SimBridge": ".sim_bridge",
    "SimTMF8820Bus": ".sim_i2c",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
