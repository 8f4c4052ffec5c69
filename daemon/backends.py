"""Build the rig's Arm and Sensor from a config. Backend modules are imported only when chosen, so that a rig with a
serial sensor never imports smbus2 and a sim rig never imports ur_rtde.

A `sim` sensor renders the scene at the arm's *actual* pose: its pose provider returns the arm's current TCP pose @
hand-eye. With the sim arm that is the arm's live pose (also mid-move); with any other arm it is the last pose the
arm reported or reached (`TrackedArm`).
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from spadscan.protocol.errors import ConfigError, MeshError, SensorModelError, SimulationError

from .config import ArmConfig, DaemonConfig, mesh_path
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

    def actual_pose(self) -> np.ndarray:
        return self.last_tcp_pose.copy()


def build_arm(cfg: ArmConfig) -> Arm:
    """The configured arm (not yet connected)."""
    if cfg.backend == "sim":
        from .arm.sim import SimArm, SimArmFaults

        return SimArm(motion_time_s=cfg.motion_time_s, speed=cfg.speed, time_scale=cfg.time_scale,
                      faults=SimArmFaults(protective_stop_on_moves=tuple(cfg.protective_stop_on_move)),
                      pose_noise_m=cfg.pose_noise_m)
    from .arm.ur import URArm

    return URArm(cfg.host, speed=cfg.speed, accel=cfg.acceleration)


def pose_provider(arm: Arm, hand_eye: np.ndarray) -> Callable[[], np.ndarray]:
    """A callable returning the sensor pose (4, 4) now: the arm's actual TCP pose @ hand-eye."""
    he = np.array(hand_eye, dtype=float)
    return lambda: arm.actual_pose() @ he


def load_scene(spec: str, offset_m: np.ndarray, where: str):
    """The sim scene mesh (trimesh, metres): a file or builtin:NAME, shifted by offset_m (3,)."""
    try:
        if spec.startswith("builtin:"):
            from spadscan.protocol.scenes import builtin_scene

            mesh = builtin_scene(spec[len("builtin:"):])
        else:
            from spadscan.protocol.mesh_io import load_mesh

            mesh = load_mesh(spec)
    except MeshError as exc:
        raise ConfigError(f"{where} mesh: {exc}") from None
    if np.any(offset_m):
        mesh = mesh.copy()
        mesh.apply_translation(np.asarray(offset_m, dtype=float))
    return mesh


def sensor_model(cfg: DaemonConfig):
    """The sensor model of the configured preset, with the sim photon overrides folded in (stored in captures)."""
    from spadscan.protocol.sensor_presets import sensor_preset

    s = cfg.sensor
    model = sensor_preset(s.preset)
    if s.backend != "sim":
        return model
    changes = {}
    if s.cycles is not None:
        changes["cycles"] = s.cycles
    if s.ambient is not None:
        changes["background"] = s.ambient
    if s.power != 1.0:
        changes["signal_scale"] = model.signal_scale * s.power
    try:
        return model.with_(**changes) if changes else model
    except SensorModelError as exc:
        raise ConfigError(f"{_where(cfg)}: [sensor]: {exc}") from None


def build_sensor(cfg: DaemonConfig, arm: Arm) -> Sensor:
    """The configured sensor (not yet connected). A sim sensor renders at `arm`'s actual pose."""
    s = cfg.sensor
    model = sensor_model(cfg)
    if s.backend == "serial":
        from .sensor import SerialSensor

        return SerialSensor(s.port, s.baud, model=model)
    if s.backend == "i2c":
        from .sensor import I2CSensor

        return I2CSensor(s.bus, s.address, s.firmware, model=model)
    from spadscan.protocol.simulator import SimSettings

    from .sensor import SimSensor

    mesh = load_scene(mesh_path(cfg), s.mesh_offset_m, f"{_where(cfg)}: [sensor]")
    try:
        settings = SimSettings(albedo=s.albedo, rays_per_zone=s.rays_per_zone).check()
    except SimulationError as exc:
        raise ConfigError(f"{_where(cfg)}: [sensor]: {exc}") from None
    return SimSensor(model, mesh, pose_provider(arm, cfg.arm.hand_eye), settings=settings, seed=s.seed,
                     frame_time_s=s.frame_time_s, silence_on_frames=s.silence_on_frames, silence_s=s.silence_s)


def build_devices(cfg: DaemonConfig) -> tuple[Arm, Sensor]:
    """Arm and sensor for the config, neither connected. Errors here happen before anything moves."""
    arm = build_arm(cfg.arm)
    if cfg.sensor.backend == "sim" and not hasattr(arm, "actual_pose"):
        arm = TrackedArm(arm)
    return arm, build_sensor(cfg, arm)


def rig_record(cfg: DaemonConfig) -> tuple[dict, dict]:
    """(rig, scene) records stored in every capture's manifest."""
    a, s = cfg.arm, cfg.sensor
    arm = {"backend": a.backend, "speed_m_s": a.speed, "acceleration_m_s2": a.acceleration}
    if a.backend == "ur":
        arm["host"] = a.host
    sensor = {"backend": s.backend, "preset": s.preset}
    sensor.update({"serial": {"port": s.port, "baud": s.baud}, "i2c": {"bus": s.bus, "address": s.address},
                   "sim": {"seed": s.seed, "rays_per_zone": s.rays_per_zone, "albedo": s.albedo}}[s.backend])
    rig = {"arm": arm, "sensor": sensor, "config": str(cfg.source) if cfg.source else None,
           "created_unix_s": round(time.time(), 3), "clock": "t_start/t_end: daemon monotonic seconds"}
    scene = {}
    if s.backend == "sim":  # the same record `spadscan simulate` writes, so the worker finds the ground truth
        spec = mesh_path(cfg)
        scene = {"builtin": spec[len("builtin:"):]} if spec.startswith("builtin:") else {"mesh": spec}
        scene.update(mesh_offset_m=np.asarray(s.mesh_offset_m).tolist(), albedo=s.albedo, seed=s.seed,
                     rays_per_zone=s.rays_per_zone)
    return rig, scene


def _where(cfg: DaemonConfig) -> str:
    return str(cfg.source) if cfg.source else "config"
