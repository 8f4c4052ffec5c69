"""Arm backend `sim`: a simulated arm (`daemon/arm/sim.py`) whose moves take time and whose faults are scheduled."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from spadscan.daemon.config_keys import key

from .base import ArmBackend


@dataclass(frozen=True)
class SimArmSettings(ArmBackend):
    """[arm] keys of backend 'sim'."""

    name: ClassVar[str] = "sim"

    motion_time_s: float | None = key(None, "float", lo=0.0, hi=600.0, unit="s")
    """Sim: a fixed duration of every move (s; 0 = instant); omitted: from distance, speed and acceleration."""
    time_scale: float = key(1.0, "float", lo=0.0, hi=1000.0, unit="")
    """Sim: multiplies every motion time (0.1 runs moves ten times faster than real)."""
    pose_noise_m: float = key(0.0, "float", lo=0.0, hi=0.01, unit="m")
    """Sim: standard deviation of the actual position around the commanded one (m)."""
    protective_stop_on_move: tuple = key((), "ints", lo=1)
    """Sim: move numbers (1 = first move) that end in a protective stop, to rehearse faults."""

    def build(self, arm):
        from spadscan.daemon.arm.sim import SimArm, SimArmFaults

        return SimArm(motion_time_s=self.motion_time_s, speed=arm.speed, time_scale=self.time_scale,
                      faults=SimArmFaults(protective_stop_on_moves=tuple(self.protective_stop_on_move)),
                      pose_noise_m=self.pose_noise_m)


BACKEND = SimArmSettings
