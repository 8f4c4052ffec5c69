"""The rig of a config: its Arm and Sensor, built by their backends (`backends/`), and the rig record every capture
stores. A sensor that renders at the arm's pose (the `sim` sensor) gets an arm that knows its pose: the sim arm's
own live pose, or, for any other arm, the last pose it reported or reached (`TrackedArm`).
"""

from __future__ import annotations

import os
import time

import numpy as np

from .config import DaemonConfig
from .devices import Arm, ArmState, Sensor


class TrackedArm(Arm):
    """Wraps an arm and remembers its latest known TCP pose (4, 4) for a sim sensor's pose provider."""

    def __init__(self, arm: Arm, home: np.ndarray | None = None):
        self.inner = arm
        self.name = arm.name
        self.last_tcp_pose = np.eye(4) if home is None else np.array(home, dtype=float)

    async def connect(self) -> None:
        await self.inner.connect()

    async def prepare(self) -> None:
        await self.inner.prepare()
        try:
            await self.state()
        except Exception:  # the pose is only a hint for the renderer; a real fault shows up on the first move
            pass

    async def release(self) -> None:
        await self.inner.release()

    async def close(self) -> None:
        await self.inner.close()

    async def move_to(self, tcp_pose: np.ndarray, speed: float, accel: float) -> None:
        await self.inner.move_to(tcp_pose, speed, accel)
        self.last_tcp_pose = np.array(tcp_pose, dtype=float)

    async def state(self) -> ArmState:
        s = await self.inner.state()
        self.last_tcp_pose = np.array(s.tcp_pose, dtype=float)
        return s

    async def stop(self) -> None:
        await self.inner.stop()

    async def reconnect(self) -> None:
        await self.inner.reconnect()

    async def clear_fault(self) -> None:
        await self.inner.clear_fault()

    async def check_poses(self, tcp_poses: np.ndarray, first_index: int = 0) -> None:
        await self.inner.check_poses(tcp_poses, first_index)

    async def read_speed_slider(self) -> None:
        await self.inner.read_speed_slider()

    def actual_pose(self) -> np.ndarray:
        return self.last_tcp_pose.copy()


def sensor_model(cfg: DaemonConfig):
    """The sensor model of the configured preset, with the backend's overrides (sim photon keys) folded in: what
    every capture stores."""
    from spadscan.protocol.sensor_presets import sensor_preset

    return cfg.sensor.device.model(sensor_preset(cfg.sensor.preset), f"{_where(cfg)}: [sensor]")


def build_arm(cfg: DaemonConfig) -> Arm:
    """The configured arm (not yet connected)."""
    return cfg.arm.device.build(cfg.arm)


def build_sensor(cfg: DaemonConfig, arm: Arm) -> Sensor:
    """The configured sensor (not yet connected); one that renders at the arm's pose renders at `arm`'s."""
    return cfg.sensor.device.build(cfg.sensor, sensor_model(cfg), arm, cfg.arm.hand_eye, f"{_where(cfg)}: [sensor]")


def build_devices(cfg: DaemonConfig) -> tuple[Arm, Sensor]:
    """Arm and sensor for the config, neither connected. Errors here happen before anything moves."""
    arm = build_arm(cfg)
    if cfg.sensor.device.renders_at_arm_pose and not hasattr(arm, "actual_pose"):
        arm = TrackedArm(arm)
    return arm, build_sensor(cfg, arm)


def preflight(cfg: DaemonConfig) -> None:
    """Each backend's checks that touch no device (device nodes present, a firmware image that parses)."""
    cfg.arm.device.preflight(f"{_where(cfg)}: [arm]")
    cfg.sensor.device.preflight(f"{_where(cfg)}: [sensor]")


def rig_record(cfg: DaemonConfig) -> tuple[dict, dict]:
    """(rig, scene) records stored in every capture's manifest."""
    a, s = cfg.arm, cfg.sensor
    arm = {"backend": a.backend, "speed_m_s": a.speed, "acceleration_m_s2": a.acceleration, **a.device.rig_record()}
    sensor = {"backend": s.backend, "preset": s.preset, **s.device.rig_record()}
    # The config's whole path: the dashboard's "start a daemon" hint gives it, to be run from any folder.
    rig = {"arm": arm, "sensor": sensor, "config": os.path.abspath(cfg.source) if cfg.source else None,
           "created_unix_s": round(time.time(), 3), "clock": "t_start/t_end: daemon monotonic seconds"}
    return rig, s.device.scene_record()


def _where(cfg: DaemonConfig) -> str:
    return str(cfg.source) if cfg.source else "config"
