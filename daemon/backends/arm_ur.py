"""Arm backend `ur`: a Universal Robots arm through the real ur_rtde client (`daemon/arm/ur.py`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from spadscan.daemon.config_keys import key
from spadscan.protocol.errors import ConfigError

from .base import ArmBackend


@dataclass(frozen=True)
class URArmSettings(ArmBackend):
    """[arm] keys of backend 'ur'."""

    name: ClassVar[str] = "ur"

    host: str | None = key(None, "str")
    """The UR controller's IP address or host name (required for 'ur')."""

    def checked(self, section, where, base):
        for name, value in (("host", self.host), ("workspace_min", section.workspace_min),
                            ("workspace_max", section.workspace_max)):
            if value is None:
                raise ConfigError(f"{where} {name} is required for backend 'ur'")
        return self

    def build(self, arm):
        from spadscan.daemon.arm.ur import URArm

        return URArm(self.host, speed=arm.speed, accel=arm.acceleration)

    def rig_record(self) -> dict:
        return {"host": self.host}


BACKEND = URArmSettings
