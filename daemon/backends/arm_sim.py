"""Arm backend `sim`: a simulated arm (`daemon/arm/sim.py`) whose moves take time and whose faults are scheduled."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from spadscan.daemon.config_keys import key
from spadscan.protocol.errors import ConfigError

from .base import ArmBackend


@dataclass(frozen=True)
class SimArmSettings(ArmBackend):
    """[arm] keys of backend 'sim'."""

    name: ClassVar[str] = "sim"

    motion_time_s: float | None = key(None, "float", lo=0.0, hi=600.0, unit="s")
    """Sim: a fixed duration of every move (s; 0 = instant; times time_scale, shorter than move_timeout_s); omitted:
    from distance, speed and acceleration."""
    time_scale: float = key(1.0, "float", lo=0.0, hi=1000.0, unit="")
    """Sim: multiplies every motion time (0.1 runs moves ten times faster than real)."""
    pose_noise_m: float = key(0.0, "float", lo=0.0, hi=0.01, unit="m")
    """Sim: standard deviation of the actual position around the commanded one (m)."""
    protective_stop_on_move: tuple = key((), "ints", lo=1)
    """Sim: move numbers (1 = first move) that end in a protective stop, to rehearse faults."""

    def checked(self, section, where, base):
        if self.motion_time_s is None:
            # Trapezoid timing: a move's time depends on its distance (a short one always fits), so no config
            # alone makes every move too slow.
            return self
        duration = self.motion_time_s * self.time_scale
        if duration >= section.move_timeout_s:
            # A fixed motion time applies to every move: each one would outlast the runner's wait for it.
            scaled = "" if self.time_scale == 1 else f" x time_scale {self.time_scale:g} = {duration:g} s"
            raise ConfigError(f"{where} motion_time_s {self.motion_time_s:g} s{scaled} is not shorter than "
                              f"move_timeout_s {section.move_timeout_s:g} s: every move would time out (every scan "
                              f"would pause at its first pose); shorten motion_time_s or time_scale, or lengthen "
                              f"move_timeout_s")
        return self

    def build(self, arm):
        from spadscan.daemon.arm.sim import SimArm, SimArmFaults

        return SimArm(motion_time_s=self.motion_time_s, speed=arm.speed, time_scale=self.time_scale,
                      faults=SimArmFaults(protective_stop_on_moves=tuple(self.protective_stop_on_move)),
                      pose_noise_m=self.pose_noise_m)


BACKEND = SimArmSettings
