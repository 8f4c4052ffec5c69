"""Sensor backend `sim`: the simulator renders a mesh at the arm's actual pose (`daemon/sensor/sim.py`).

Its pose provider returns the arm's current TCP pose @ hand-eye. With the sim arm that is the arm's live pose (also
mid-move); with any other arm it is the last pose the arm reported or reached (the rig wraps it in `TrackedArm`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, ClassVar

import numpy as np

from spadscan.daemon.config_keys import key
from spadscan.protocol.errors import ConfigError, MeshError, SensorModelError, SimulationError

from .base import SensorBackend

BUILTIN = "builtin:"


@dataclass(frozen=True)
class SimSensorSettings(SensorBackend):
    """[sensor] keys of backend 'sim'."""

    name: ClassVar[str] = "sim"
    renders_at_arm_pose: ClassVar[bool] = True
    renders_with_model: ClassVar[bool] = True
    model_keys: ClassVar[dict[str, str]] = {"signal_scale": "power", "background": "ambient", "cycles": "cycles"}

    mesh: str | None = key(None, "str")
    """Sim: the scene, a mesh file (metres; STL in mm is detected) or builtin:NAME (required for 'sim')."""
    mesh_offset_m: np.ndarray = key([0.0, 0.0, 0.0], "vec3", unit="m")
    """Sim: where the mesh's origin sits in the arm's base frame [x, y, z] (m)."""
    frame_time_s: float = key(0.0, "float", lo=0.0, hi=60.0, unit="s")
    """Sim: exposure time of one frame (s; the real sensor takes ~0.3); shorter than frame_timeout_s."""
    seed: int = key(0, "int", lo=0, hi=2**63 - 1)
    """Sim: random seed of the photon noise."""
    power: float = key(1.0, "float", lo=0.0, hi=1e9)
    """Sim: laser power relative to the preset (multiplies its signal_scale)."""
    ambient: float | None = key(None, "float", lo=0.0, hi=1.0, unit="photons/bin/cycle")
    """Sim: ambient background, photons per bin per cycle (default: the preset's)."""
    cycles: int | None = key(None, "int", lo=1, hi=10**10)
    """Sim: laser cycles per histogram (default: the preset's)."""
    albedo: float = key(1.0, "float", lo=0.0, hi=1000.0)
    """Sim: Lambertian albedo of every surface of the mesh."""
    rays_per_zone: int = key(4096, "int", lo=1, hi=10**7)
    """Sim: rays cast per zone per frame (fewer renders faster, coarser)."""
    silence_on_frames: tuple = key((), "ints", lo=0)
    """Sim: frame numbers (0 = the first frame the sensor delivers after the daemon started, counted across scans)
    at which the sensor falls silent for silence_s instead, to rehearse faults."""
    silence_s: float = key(0.0, "float", lo=0.0, hi=3600.0, unit="s")
    """Sim: how long each scheduled silence lasts (s; > 0 when silence_on_frames is set)."""

    def checked(self, section, where, base):
        if self.mesh is None:
            raise ConfigError(f"{where} mesh is required for backend 'sim'")
        if self.silence_on_frames and self.silence_s <= 0:
            raise ConfigError(f"{where} silence_on_frames {list(self.silence_on_frames)} needs silence_s > 0 (s)")
        if 2 * self.frame_time_s >= section.frame_timeout_s:
            # The runner waits frame_timeout_s, from when the arm has settled, for a frame that began after it
            # settled. The sim sensor measures back to back: the frame under way when the arm settles is dropped, so
            # the first one kept begins up to frame_time_s later and ends up to two frame times after the settle.
            # A wait shorter than that pauses the scan at pose after pose (with a fixed move time, at every pose).
            raise ConfigError(f"{where} frame_time_s {self.frame_time_s:g} s is not under half of frame_timeout_s "
                              f"{section.frame_timeout_s:g} s: the first frame begun after the arm settles can end "
                              f"two frame times ({2 * self.frame_time_s:g} s) after it, past the wait (scans would "
                              f"pause at pose after pose); shorten frame_time_s or lengthen frame_timeout_s")
        if self.mesh.startswith(BUILTIN):
            return self
        p = Path(os.path.expanduser(self.mesh))
        mesh = str(p if p.is_absolute() or base is None else base / p)
        if not Path(mesh).is_file():
            raise ConfigError(f"{where} mesh {mesh}: no such file (or use builtin:NAME)")
        return replace(self, mesh=mesh)

    def model(self, preset, where):
        changes = {}
        if self.cycles is not None:
            changes["cycles"] = self.cycles
        if self.ambient is not None:
            changes["background"] = self.ambient
        if self.power != 1.0:
            changes["signal_scale"] = preset.signal_scale * self.power
        try:
            return preset.with_(**changes) if changes else preset
        except SensorModelError as exc:
            raise ConfigError(f"{where}: {exc}") from None

    @classmethod
    def preset_value(cls, field, value, rig):
        # As `model` sets them: power multiplies the preset's signal_scale (absent: 1, the preset's own; 0 hides it),
        # ambient and cycles replace background and cycles (absent or null: the preset's own).
        if field == "signal_scale":
            power = rig.get("power", 1.0)
            if not isinstance(power, (int, float)) or isinstance(power, bool) or power <= 0:
                return None
            return value / power if isinstance(value, (int, float)) else None
        key_name = cls.model_keys.get(field)
        if key_name is not None and rig.get(key_name) is not None:
            return None
        return value

    def build(self, sensor, model, arm, hand_eye, where):
        from spadscan.protocol.simulator import SimSettings

        from spadscan.daemon.sensor import SimSensor

        mesh = load_scene(self.mesh, self.mesh_offset_m, where)
        try:
            settings = SimSettings(albedo=self.albedo, rays_per_zone=self.rays_per_zone).check()
        except SimulationError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        return SimSensor(model, mesh, pose_provider(arm, hand_eye), settings=settings, seed=self.seed,
                         frame_time_s=self.frame_time_s, silence_on_frames=self.silence_on_frames,
                         silence_s=self.silence_s)

    def rig_record(self) -> dict:
        # The keys that set the sensor model (`model_keys`; null: the preset's own), so that a resume compares them
        # key to key and puts any other difference of the model down to the preset.
        return {"seed": self.seed, "rays_per_zone": self.rays_per_zone, "albedo": self.albedo, "power": self.power,
                "ambient": self.ambient, "cycles": self.cycles}

    def scene_record(self) -> dict:
        # The same record `spadscan simulate` writes, so the worker finds the ground truth.
        spec = self.mesh
        scene = {"builtin": spec[len(BUILTIN):]} if spec.startswith(BUILTIN) else {"mesh": spec}
        scene.update(mesh_offset_m=np.asarray(self.mesh_offset_m).tolist(), albedo=self.albedo, seed=self.seed,
                     rays_per_zone=self.rays_per_zone)
        return scene


def pose_provider(arm, hand_eye: np.ndarray) -> Callable[[], np.ndarray]:
    """A callable returning the sensor pose (4, 4) now: the arm's actual TCP pose @ hand-eye."""
    he = np.array(hand_eye, dtype=float)
    return lambda: arm.actual_pose() @ he


def load_scene(spec: str, offset_m: np.ndarray, where: str):
    """The sim scene mesh (trimesh, metres): a file or builtin:NAME, shifted by offset_m (3,)."""
    try:
        if spec.startswith(BUILTIN):
            from spadscan.protocol.scenes import builtin_scene

            mesh = builtin_scene(spec[len(BUILTIN):])
        else:
            from spadscan.protocol.mesh_io import load_mesh

            mesh = load_mesh(spec)
    except MeshError as exc:
        raise ConfigError(f"{where} mesh: {exc}") from None
    if np.any(offset_m):
        mesh = mesh.copy()
        mesh.apply_translation(np.asarray(offset_m, dtype=float))
    return mesh


BACKEND = SimSensorSettings
