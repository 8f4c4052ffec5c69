"""The rig config (`spadscan daemon --config rig.toml`): dataclasses with one docstring per key, validated on load.

Units at this edge are the user's: metres, seconds and degrees (key names say which where it is not obvious).
Every problem is one ConfigError line naming the file and the key, raised before any device is touched. Relative
paths are taken relative to the config file's folder. `examples/README.md` documents every key for users.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from spadscan.protocol.errors import ConfigError

from .client import default_socket_path

SOCKET_PATH_MAX = 107  # bytes in sockaddr_un.sun_path, less the terminating NUL


@dataclass(frozen=True)
class Key:
    """How one config key is read: its kind, its range (lo/hi; open bounds when lo_open/hi_open), its unit."""

    kind: str  # str, float, int, bool, path, vec3, mat4, choice, ints
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple = ()
    unit: str = ""
    backends: tuple[str, ...] = ()  # the backends the key applies to; empty: all


def key(default, kind: str, **spec):
    """A dataclass field that carries its Key spec (mutable defaults become factories)."""
    if isinstance(default, (list, np.ndarray)):
        return field(default_factory=lambda: np.array(default, dtype=float), metadata={"key": Key(kind, **spec)})
    return field(default=default, metadata={"key": Key(kind, **spec)})


@dataclass(frozen=True)
class ArmConfig:
    """[arm]: the robot that carries the sensor."""

    backend: str = key("sim", "choice", choices=("ur", "sim"))
    """'ur' (a Universal Robots arm through ur_rtde) or 'sim' (a simulated arm)."""
    host: str | None = key(None, "str", backends=("ur",))
    """The UR controller's IP address or host name (required for 'ur')."""
    speed: float = key(0.1, "float", lo=0.0, hi=1.0, lo_open=True, unit="m/s")
    """Linear TCP speed of every move (m/s)."""
    acceleration: float = key(0.5, "float", lo=0.0, hi=5.0, lo_open=True, unit="m/s^2")
    """Linear TCP acceleration of every move (m/s^2)."""
    hand_eye: np.ndarray = key(np.eye(4).tolist(), "mat4")
    """4x4 transform from the tool flange (TCP) to the sensor, metres: sensor pose = TCP pose x hand_eye."""
    workspace_min: np.ndarray | None = key(None, "vec3", unit="m")
    """Lowest corner [x, y, z] of the box every TCP position must lie in, base frame (m); required for 'ur'."""
    workspace_max: np.ndarray | None = key(None, "vec3", unit="m")
    """Highest corner [x, y, z] of that box (m); required for 'ur'."""
    min_reach_m: float = key(0.0, "float", lo=0.0, hi=10.0, unit="m")
    """Smallest allowed distance of the TCP from the base origin (m); keeps moves clear of the arm's own base."""
    max_reach_m: float | None = key(None, "float", lo=0.0, hi=10.0, lo_open=True, unit="m")
    """Largest allowed distance of the TCP from the base origin (m), e.g. 0.85 for a UR5e."""
    move_timeout_s: float = key(60.0, "float", lo=0.0, hi=3600.0, lo_open=True, unit="s")
    """How long one move may take before the scan pauses with a timeout (s)."""
    motion_time_s: float | None = key(None, "float", lo=0.0, hi=600.0, unit="s", backends=("sim",))
    """Sim: a fixed duration of every move (s; 0 = instant); omitted: from distance, speed and acceleration."""
    time_scale: float = key(1.0, "float", lo=0.0, hi=1000.0, unit="", backends=("sim",))
    """Sim: multiplies every motion time (0.1 runs moves ten times faster than real)."""
    pose_noise_m: float = key(0.0, "float", lo=0.0, hi=0.01, unit="m", backends=("sim",))
    """Sim: standard deviation of the actual position around the commanded one (m)."""
    protective_stop_on_move: tuple = key((), "ints", lo=1, backends=("sim",))
    """Sim: move numbers (1 = first move) that end in a protective stop, to rehearse faults."""


@dataclass(frozen=True)
class SensorConfig:
    """[sensor]: the time-of-flight sensor on the flange."""

    backend: str = key("sim", "choice", choices=("serial", "i2c", "sim"))
    """'serial' (TMF8820 behind the Arduino bridge), 'i2c' (TMF8820 on an I2C bus) or 'sim' (simulated)."""
    preset: str = key("tmf8820", "choice", choices=("tmf8820", "lcspc-sim"))
    """Sensor model preset stored with every capture ('tmf8820' or 'lcspc-sim')."""
    port: str | None = key(None, "str", backends=("serial",))
    """Serial device of the bridge, e.g. /dev/ttyACM0 (required for 'serial')."""
    baud: int = key(1_000_000, "int", lo=1200, hi=12_000_000, backends=("serial",))
    """Baud rate of the bridge (the firmware prints at 1000000; some sketches at 115200)."""
    bus: int | None = key(None, "int", lo=0, hi=255, backends=("i2c",))
    """I2C bus number, /dev/i2c-N (required for 'i2c')."""
    address: int = key(0x41, "int", lo=0x08, hi=0x77, backends=("i2c",))
    """7-bit I2C address of the sensor (0x41)."""
    firmware: Path | None = key(None, "path", backends=("i2c",))
    """Path to your copy of the ams application image (.hex) downloaded at boot (required for 'i2c'; never shipped)."""
    mesh: str | None = key(None, "str", backends=("sim",))
    """Sim: the scene, a mesh file (metres; STL in mm is detected) or builtin:NAME (required for 'sim')."""
    mesh_offset_m: np.ndarray = key([0.0, 0.0, 0.0], "vec3", unit="m", backends=("sim",))
    """Sim: where the mesh's origin sits in the arm's base frame [x, y, z] (m)."""
    frame_time_s: float = key(0.0, "float", lo=0.0, hi=60.0, unit="s", backends=("sim",))
    """Sim: exposure time of one frame (s; the real sensor takes ~0.3)."""
    seed: int = key(0, "int", lo=0, hi=2**63 - 1, backends=("sim",))
    """Sim: random seed of the photon noise."""
    power: float = key(1.0, "float", lo=0.0, hi=1e9, backends=("sim",))
    """Sim: laser power relative to the preset (multiplies its signal_scale)."""
    ambient: float | None = key(None, "float", lo=0.0, hi=1.0, unit="photons/bin/cycle", backends=("sim",))
    """Sim: ambient background, photons per bin per cycle (default: the preset's)."""
    cycles: int | None = key(None, "int", lo=1, hi=10**10, backends=("sim",))
    """Sim: laser cycles per histogram (default: the preset's)."""
    albedo: float = key(1.0, "float", lo=0.0, hi=1000.0, backends=("sim",))
    """Sim: Lambertian albedo of every surface of the mesh."""
    rays_per_zone: int = key(4096, "int", lo=1, hi=10**7, backends=("sim",))
    """Sim: rays cast per zone per frame (fewer renders faster, coarser)."""
    silence_on_frames: tuple = key((), "ints", lo=0, backends=("sim",))
    """Sim: frame numbers (0 = the first frame the sensor delivers after the daemon started, counted across scans)
    at which the sensor falls silent for silence_s instead, to rehearse faults."""
    silence_s: float = key(0.0, "float", lo=0.0, hi=3600.0, unit="s", backends=("sim",))
    """Sim: how long each scheduled silence lasts (s; > 0 when silence_on_frames is set)."""
    frame_timeout_s: float = key(5.0, "float", lo=0.0, hi=600.0, lo_open=True, unit="s")
    """A sensor that delivers no frame for this long is silent: the scan pauses (s)."""


@dataclass(frozen=True)
class ScanConfig:
    """[scan]: defaults of every scan; `spadscan ctl scan` options override them per scan."""

    views: int = key(128, "int", lo=1, hi=10_000)
    """Number of sensor poses. 128, like the paper's real captures (120-128 per scan): at 64 the reconstruction of a
    thin-walled object (the built-in goblet) is short of data and depends on the seed (benchmarks/RESULTS.md)."""
    schedule: str = key("fibonacci", "choice", choices=("fibonacci", "rings"))
    """'fibonacci' (a Fibonacci spiral over the hemisphere, the dataset's layout) or 'rings' (elevation rings)."""
    rings: int = key(4, "int", lo=1, hi=1000)
    """'rings' only: number of elevation rings; views must be a multiple of it."""
    radius_m: float = key(0.5, "float", lo=0.0, hi=5.0, lo_open=True, unit="m")
    """Distance from the sensor to the target point (m)."""
    target: np.ndarray = key([0.0, 0.0, 0.0], "vec3", unit="m")
    """The point every view looks at, base frame [x, y, z] (m)."""
    min_elevation_deg: float = key(10.0, "float", lo=-90.0, hi=90.0, unit="deg")
    """Lowest elevation of a view above the target's horizontal plane (degrees)."""
    max_elevation_deg: float = key(80.0, "float", lo=-90.0, hi=90.0, unit="deg")
    """Highest elevation of a view (degrees)."""
    jitter_deg: float = key(0.0, "float", lo=0.0, hi=45.0, unit="deg")
    """Largest random tilt of a view away from the target (degrees; 0 = every view looks at the target)."""
    seed: int = key(0, "int", lo=0, hi=2**63 - 1)
    """Random seed of the jitter."""
    order: str = key("nearest", "choice", choices=("nearest", "serpentine", "planned"))
    """Visiting order: 'nearest' (greedy nearest neighbour), 'serpentine' (ring by ring, alternating direction)
    or 'planned' (as generated)."""
    frames_per_pose: int = key(1, "int", lo=1, hi=100_000)
    """Frames captured at each pose, each stored as its own measurement (never summed)."""
    settle_s: float = key(0.2, "float", lo=0.0, hi=60.0, unit="s")
    """Wait after the arm stops before frames count (s); frames that began earlier are dropped."""
    chunk_size: int = key(64, "int", lo=1, hi=1_000_000)
    """The largest chunk, in measurements; at least frames_per_pose (a pose is never split). The daemon publishes each
    pose as its own chunk as soon as it is complete, so this caps a chunk rather than batching poses."""


@dataclass(frozen=True)
class DaemonConfig:
    """The whole rig config."""

    captures: Path = key(Path("captures"), "path")
    """Captures root: a scan named N is written to <captures>/N/."""
    socket: Path = key(None, "path")
    """Control socket path (mode 0600); default (the same as `spadscan ctl`'s): $SPADSCAN_SOCKET, else
    $XDG_RUNTIME_DIR/spadscan.sock, else /tmp/spadscan-<uid>.sock."""
    auto_resume: bool = key(False, "bool")
    """Resume an interrupted scan by itself at start-up (otherwise it waits, paused, for `ctl resume`)."""
    arm: ArmConfig = field(default_factory=ArmConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    scan: ScanConfig = field(default_factory=ScanConfig)
    source: Path | None = None
    """The file this config was read from."""


# ---- reading ---------------------------------------------------------------------------------------------------------
def load_config(path) -> DaemonConfig:
    """Read and validate a rig config file. Raises one-line ConfigError naming the file and key."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return config_from_dict(data, path)


def config_from_dict(data: dict, path: Path) -> DaemonConfig:
    base = path.resolve().parent
    tables = {"arm": ArmConfig, "sensor": SensorConfig, "scan": ScanConfig}
    top = {k: v for k, v in data.items() if k not in tables}
    sections = {}
    for name, cls in tables.items():
        table = data.get(name, {})
        if not isinstance(table, dict):
            raise ConfigError(f"{path}: [{name}] must be a table")
        sections[name] = read_section(cls, table, f"{path}: [{name}]", base)
    values = _read_values(DaemonConfig, top, f"{path}:", base, skip=("arm", "sensor", "scan", "source"))
    values.setdefault("captures", base / "captures")
    if values.get("socket") is None:
        values["socket"] = Path(default_socket_path())
    cfg = DaemonConfig(**values, **sections, source=path)
    _check_arm(cfg.arm, f"{path}: [arm]")
    _check_sensor(cfg.sensor, f"{path}: [sensor]")
    check_scan(cfg.scan, f"{path}: [scan]")
    _check_paths(cfg, str(path))
    return cfg


def read_section(cls, table: dict, where: str, base: Path | None = None):
    """Build a section's dataclass from a TOML table; unknown keys, bad values and keys that do not apply to the
    section's backend are one-line errors."""
    obj = cls(**_read_values(cls, table, where, base))
    backend = getattr(obj, "backend", None)
    for f in fields(cls):
        spec = f.metadata.get("key")
        if spec and spec.backends and backend not in spec.backends and f.name in table:
            raise ConfigError(f"{where} {f.name} applies only to backend {' or '.join(map(repr, spec.backends))}, "
                              f"not {backend!r}")
    return obj


def scan_with(base: ScanConfig, overrides: dict, where: str = "scan request") -> ScanConfig:
    """The scan config with some keys replaced (from `ctl scan`), validated like the file's [scan] table."""
    scan = replace(base, **_read_values(ScanConfig, overrides, where, None))
    check_scan(scan, where)
    return scan


def scan_request(base: ScanConfig, overrides: dict, where: str = "scan request") -> ScanConfig:
    """scan_with for a request (`ctl scan`): also refuses keys that the request sets and its schedule ignores, so
    that `--rings 3` with the Fibonacci schedule is not silently dropped."""
    scan = scan_with(base, overrides, where)
    if "rings" in overrides and scan.schedule != "rings":
        raise ConfigError(f"{where} rings applies only to schedule 'rings', not {scan.schedule!r} (add "
                          f"--schedule rings, or leave --rings out)")
    return scan


def scan_to_dict(scan: ScanConfig) -> dict:
    """JSON form of a scan config (stored in the capture's manifest, read back by `scan_from_dict`)."""
    out = {}
    for f in fields(scan):
        v = getattr(scan, f.name)
        out[f.name] = v.tolist() if isinstance(v, np.ndarray) else v
    return out


def _read_values(cls, table: dict, where: str, base: Path | None, skip=()) -> dict:
    known = {f.name: f for f in fields(cls) if f.name not in skip}
    values = {}
    for name, value in table.items():
        if name not in known:
            raise ConfigError(f"{where} unknown key {name!r} (known: {', '.join(known)})")
        values[name] = _coerce(value, known[name].metadata["key"], f"{where} {name}", base)
    return values


def _coerce(value, spec: Key, where: str, base: Path | None):
    k = spec.kind
    if k == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"{where} = {value!r} must be true or false")
        return value
    if k in ("str", "choice", "path"):
        if not isinstance(value, str) or not value.strip():
            raise ConfigError(f"{where} = {value!r} must be a non-empty string")
        if k == "choice" and value not in spec.choices:
            raise ConfigError(f"{where} = {value!r} must be one of {', '.join(map(repr, spec.choices))}")
        if k == "path":
            p = Path(os.path.expanduser(value))
            return p if (p.is_absolute() or base is None) else base / p
        return value
    if k == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} = {value!r} must be an integer")
        _check_range(value, spec, where)
        return value
    if k == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{where} = {value!r} must be a finite number{_unit(spec)}")
        _check_range(float(value), spec, where)
        return float(value)
    if k == "ints":
        if not isinstance(value, list) or any(isinstance(v, bool) or not isinstance(v, int) for v in value):
            raise ConfigError(f"{where} = {value!r} must be a list of integers")
        for v in value:
            _check_range(v, spec, where)
        return tuple(value)
    shape = (3,) if k == "vec3" else (4, 4)
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != shape or not np.all(np.isfinite(arr)) or _has_bool(value):
        what = "[x, y, z]" if k == "vec3" else "a 4x4 array of numbers (4 rows of 4)"
        raise ConfigError(f"{where} = {value!r} must be {what}{_unit(spec)}")
    if k == "mat4":
        _check_rigid(arr, where)
    return arr


def _has_bool(value) -> bool:
    if isinstance(value, list):
        return any(_has_bool(v) for v in value)
    return isinstance(value, bool)


def _unit(spec: Key) -> str:
    return f" ({spec.unit})" if spec.unit else ""


def _check_range(v, spec: Key, where: str) -> None:
    lo_bad = spec.lo is not None and (v <= spec.lo if spec.lo_open else v < spec.lo)
    hi_bad = spec.hi is not None and v > spec.hi
    if lo_bad or hi_bad:
        lo = "-inf" if spec.lo is None else _bound(spec.lo, spec)
        hi = "inf" if spec.hi is None else _bound(spec.hi, spec)
        raise ConfigError(f"{where} = {v!r}{_unit(spec)} is outside {'(' if spec.lo_open else '['}{lo}, {hi}]")


def _bound(v: float, spec: Key) -> str:
    """A range bound as the user types it: an integer key's in full (9223372036854775807, not 9.22337e+18)."""
    return str(int(v)) if spec.kind in ("int", "ints") else f"{v:g}"


def _check_rigid(m: np.ndarray, where: str) -> None:
    r = m[:3, :3]
    if (np.abs(r @ r.T - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(r) - 1) > 1e-4
            or np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9):
        raise ConfigError(f"{where} is not a rigid transform (rotation must be orthonormal with det +1, last row "
                          f"[0, 0, 0, 1]; translation in metres)")
    if np.abs(m[:3, 3]).max() > 1.0:
        raise ConfigError(f"{where} translation {m[:3, 3].tolist()} exceeds 1 m: give it in metres")


# ---- cross-key checks --------------------------------------------------------------------------------------------
def _check_arm(arm: ArmConfig, where: str) -> None:
    if arm.backend == "ur":
        for name in ("host", "workspace_min", "workspace_max"):
            if getattr(arm, name) is None:
                raise ConfigError(f"{where} {name} is required for backend 'ur'")
    if (arm.workspace_min is None) != (arm.workspace_max is None):
        raise ConfigError(f"{where} workspace_min and workspace_max must be given together")
    if arm.workspace_min is not None and np.any(arm.workspace_min >= arm.workspace_max):
        raise ConfigError(f"{where} workspace_min {arm.workspace_min.tolist()} must be below workspace_max "
                          f"{arm.workspace_max.tolist()} on every axis (m)")
    if arm.max_reach_m is not None and arm.max_reach_m <= arm.min_reach_m:
        raise ConfigError(f"{where} max_reach_m {arm.max_reach_m} must exceed min_reach_m {arm.min_reach_m} (m)")


def _check_sensor(sensor: SensorConfig, where: str) -> None:
    required = {"serial": ("port",), "i2c": ("bus", "firmware"), "sim": ("mesh",)}[sensor.backend]
    for name in required:
        if getattr(sensor, name) is None:
            raise ConfigError(f"{where} {name} is required for backend {sensor.backend!r}")
    if sensor.silence_on_frames and sensor.silence_s <= 0:
        raise ConfigError(f"{where} silence_on_frames {list(sensor.silence_on_frames)} needs silence_s > 0 (s)")
    if sensor.backend in ("serial", "i2c") and sensor.preset != "tmf8820":
        raise ConfigError(f"{where} preset {sensor.preset!r} does not describe a TMF8820 (backend "
                          f"{sensor.backend!r} needs preset 'tmf8820')")


def check_scan(scan: ScanConfig, where: str) -> None:
    """Cross-key checks of a scan config (elevation order, rings, chunk size)."""
    single_ring = scan.schedule == "rings" and scan.rings == 1  # its elevation is midway: min = max places it
    if scan.min_elevation_deg > scan.max_elevation_deg or (scan.min_elevation_deg == scan.max_elevation_deg
                                                           and not single_ring):
        raise ConfigError(f"{where} min_elevation_deg {scan.min_elevation_deg:g} must be below max_elevation_deg "
                          f"{scan.max_elevation_deg:g} (degrees; equal only for one ring: schedule 'rings', rings 1)")
    if scan.schedule == "rings" and scan.views % scan.rings:
        raise ConfigError(f"{where} views {scan.views} must be a multiple of rings {scan.rings}")
    if scan.chunk_size < scan.frames_per_pose:
        raise ConfigError(f"{where} chunk_size {scan.chunk_size} is smaller than frames_per_pose "
                          f"{scan.frames_per_pose}: a pose must fit in one chunk so that it is published whole")


def _check_paths(cfg: DaemonConfig, where: str) -> None:
    s = cfg.sensor
    if s.backend == "i2c" and not s.firmware.is_file():
        raise ConfigError(f"{where}: [sensor] firmware {s.firmware}: no such file (point it at your copy of the "
                          f"ams application image)")
    if s.backend == "sim" and not s.mesh.startswith("builtin:"):
        mesh = mesh_path(cfg)
        if not Path(mesh).is_file():
            raise ConfigError(f"{where}: [sensor] mesh {mesh}: no such file (or use builtin:NAME)")
    if len(os.fsencode(str(cfg.socket))) > SOCKET_PATH_MAX:
        raise ConfigError(f"{where}: socket path {cfg.socket} is longer than {SOCKET_PATH_MAX} bytes (Unix limit)")
    if not cfg.socket.parent.is_dir():
        raise ConfigError(f"{where}: socket folder {cfg.socket.parent}: no such folder")
    root = cfg.captures
    probe = root if root.exists() else root.parent
    if root.exists() and not root.is_dir():
        raise ConfigError(f"{where}: captures {root} exists and is not a folder")
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise ConfigError(f"{where}: captures {root}: folder {probe} is missing or not writable")


def mesh_path(cfg: DaemonConfig) -> str:
    """The sim mesh spec with a relative file path resolved against the config file's folder."""
    spec = cfg.sensor.mesh
    if spec is None or spec.startswith("builtin:"):
        return spec
    p = Path(os.path.expanduser(spec))
    return str(p if p.is_absolute() or cfg.source is None else cfg.source.resolve().parent / p)
