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
    unattended_resume_ok: ClassVar[bool] = False

    host: str | None = key(None, "str")
    """The UR controller's IP address or host name (required for 'ur')."""
    watchdog_hz: float = key(2.0, "float", lo=0.5, hi=100.0, unit="Hz")
    """The controller's RTDE watchdog: it stops the arm when the daemon sends nothing for 1/watchdog_hz s (a killed,
    stopped or hung daemon)."""
    allow_auto_resume: bool = key(False, "bool")
    """Confirms `auto_resume = true` for this real arm: the daemon may then move it after a restart with nobody at
    the rig (only for a guarded cell)."""

    def checked(self, section, where, base):
        for name, value in (("host", self.host), ("workspace_min", section.workspace_min),
                            ("workspace_max", section.workspace_max)):
            if value is None:
                raise ConfigError(f"{where} {name} is required for backend 'ur'")
        return self

    def build(self, arm):
        from spadscan.daemon.arm.ur import URArm

        return URArm(self.host, speed=arm.speed, accel=arm.acceleration, watchdog_hz=self.watchdog_hz)

    def confirms_unattended_resume(self) -> bool:
        return self.allow_auto_resume

    def rig_record(self) -> dict:
        return {"host": self.host}


BACKEND = URArmSettings
