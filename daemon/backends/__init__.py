"""The registry of arm and sensor backends: each module of this package that defines `BACKEND` (a settings class,
see `base.py`) is one backend, found by its `name`. Adding a backend is adding one module here.

    ARM_BACKENDS     {"sim": SimArmSettings, "ur": URArmSettings}
    SENSOR_BACKENDS  {"i2c": ..., "serial": ..., "sim": SimSensorSettings}

The modules hold configuration and checks only; each imports its device classes (and their libraries: ur_rtde,
pyserial, smbus2) inside `build`, so finding them all costs nothing and loads no hardware library.
"""

from __future__ import annotations

import importlib
import pkgutil

from .base import ArmBackend, BackendSettings, SensorBackend
from .sensor_sim import pose_provider


def _discover() -> tuple[dict[str, type[ArmBackend]], dict[str, type[SensorBackend]]]:
    arms, sensors = {}, {}
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        cls = getattr(importlib.import_module(f"{__name__}.{info.name}"), "BACKEND", None)
        if cls is None:
            continue
        registry = arms if issubclass(cls, ArmBackend) else sensors
        if cls.name in registry:
            raise RuntimeError(f"two backends are named {cls.name!r}: {registry[cls.name].__module__} and "
                               f"{cls.__module__}")
        registry[cls.name] = cls
    return arms, sensors


ARM_BACKENDS, SENSOR_BACKENDS = _discover()

__all__ = ["ARM_BACKENDS", "SENSOR_BACKENDS", "ArmBackend", "BackendSettings", "SensorBackend", "pose_provider"]
