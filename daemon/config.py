"""The rig config (`spadscan daemon --config rig.toml`): dataclasses with one docstring per key, validated on load.

Units at this edge are the user's: metres, seconds and degrees (key names say which where it is not obvious).
Every problem is one ConfigError line naming the file and the key, raised before any device is touched. Relative
paths are taken relative to the config file's folder. `examples/README.md` documents every key for users.
"""

from __future__ import annotations

import difflib
import os
import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from spadscan.protocol.errors import ConfigError
from spadscan.protocol.folders import check_folder_option, folder_problem, not_a_folder
from spadscan.protocol.schedules import ring_at_pole_deg

from .backends import ARM_BACKENDS, SENSOR_BACKENDS, ArmBackend, SensorBackend
from .client import default_socket_path
from .config_keys import key, key_names, read_values

SOCKET_PATH_MAX = 107  # bytes in sockaddr_un.sun_path, less the terminating NUL


@dataclass(frozen=True)
class ArmConfig:
    """[arm]: the robot that carries the sensor. The keys below apply to every backend; each backend's own keys
    (`backends/arm_*.py`) are read from the same table into `device`."""

    backend: str = key("sim", "choice", choices=tuple(ARM_BACKENDS))
    """'ur' (a Universal Robots arm through ur_rtde) or 'sim' (a simulated arm)."""
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
    keepout_radius_m: float = key(0.0, "float", lo=0.0, hi=10.0, unit="m")
    """Smallest allowed horizontal distance from the base's vertical axis (m): a cylinder around the arm's own column
    that the TCP, the sensor and its bracket, and every straight move, must keep out of."""
    bracket_radius_m: float = key(0.0, "float", lo=0.0, hi=1.0, unit="m")
    """Radius of the bracket and sensor around the line from the flange to the sensor (m): that capsule, not only the
    flange, must stay inside the workspace and clear of the base."""
    move_timeout_s: float = key(60.0, "float", lo=0.0, hi=3600.0, lo_open=True, unit="s")
    """How long one move may take before the scan pauses with a timeout (s)."""
    device: ArmBackend = field(default_factory=ARM_BACKENDS["sim"])
    """The chosen backend's own keys (its settings class, found once by `backend`)."""


@dataclass(frozen=True)
class SensorConfig:
    """[sensor]: the time-of-flight sensor on the flange. The keys below apply to every backend; each backend's own
    keys (`backends/sensor_*.py`) are read from the same table into `device`."""

    backend: str = key("sim", "choice", choices=tuple(SENSOR_BACKENDS))
    """'serial' (TMF8820 behind the Arduino bridge), 'i2c' (TMF8820 on an I2C bus) or 'sim' (simulated)."""
    preset: str = key("tmf8820", "choice", choices=("tmf8820", "lcspc-sim"))
    """Sensor model preset stored with every capture ('tmf8820' or 'lcspc-sim')."""
    frame_timeout_s: float = key(5.0, "float", lo=0.0, hi=600.0, lo_open=True, unit="s")
    """A sensor that delivers no frame for this long is silent: the scan pauses (s)."""
    device: SensorBackend = field(default_factory=SENSOR_BACKENDS["sim"])
    """The chosen backend's own keys (its settings class, found once by `backend`)."""


@dataclass(frozen=True)
class ScanConfig:
    """[scan]: defaults of every scan; `spadscan ctl scan` options override them per scan."""

    views: int = key(128, "int", lo=1, hi=10_000)
    """Number of sensor poses. 128, like the paper's real captures (120-128 per scan): at 64 the reconstruction of a
    thin-walled object (the built-in goblet) is short of data and depends on the seed (benchmarks/RESULTS.md)."""
    schedule: str = key("fibonacci", "choice", choices=("fibonacci", "rings", "adaptive"))
    """'fibonacci' (a Fibonacci spiral over the hemisphere, the dataset's layout), 'rings' (elevation rings) or
    'adaptive' (a few well-spread views first, then before each pose the best view a live reconstruction ranks in the
    capture's next_views.json, else the next pose of a Fibonacci plan of `views` poses)."""
    rings: int = key(4, "int", lo=1, hi=1000)
    """'rings' only: number of elevation rings; views must be a multiple of it."""
    radius_m: float = key(0.5, "float", lo=0.0, hi=5.0, lo_open=True, unit="m")
    """Distance from the sensor to the target point (m)."""
    target: np.ndarray = key([0.0, 0.0, 0.0], "vec3", unit="m")
    """The point every view looks at, base frame [x, y, z] (m)."""
    min_elevation_deg: float = key(10.0, "float", lo=-90.0, hi=90.0, unit="deg")
    """Lowest elevation of a view above the target's horizontal plane (degrees)."""
    max_elevation_deg: float = key(80.0, "float", lo=-90.0, hi=90.0, unit="deg")
    """Highest elevation of a view (degrees). Rings stand at both ends of the band, so 'rings' needs it below 90: a
    ring at 90 would be one viewpoint taken views/rings times (refused)."""
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
    initial_views: int = key(16, "int", lo=1, hi=10_000)
    """'adaptive' only: the well-spread views taken before any ranking is used (at most `views`)."""
    min_view_spacing_deg: float = key(5.0, "float", lo=0.0, hi=90.0, unit="deg")
    """'adaptive' only: a ranked view closer than this to a pose already taken (the angle between the two as seen
    from the target, degrees) is passed over; so is a fallback pose while another one is farther. At 0 only a view
    already taken (within `protocol.next_views.SAME_VIEW_DEG`) is passed over: a scan never takes one view twice."""
    next_views_max_age_s: float = key(60.0, "float", lo=0.0, hi=86_400.0, lo_open=True, unit="s")
    """'adaptive' only: a next_views.json older than this (s, by its created_utc) is stale: the fallback plan is
    taken."""
    next_views_max_lag: int = key(8, "int", lo=0, hi=10_000)  # below 2 is refused by check_scan, saying why
    """'adaptive' only: a next_views.json ranked this many poses or more before the pose being chosen is stale. At
    least 2: the daemon chooses each pose while the one before it is still being captured, so the freshest ranking
    is already 1 pose behind, and at 1 (or 0) no ranking would ever be taken."""
    stop_when_converged: bool = key(False, "bool")
    """'adaptive' only: end the scan (complete, with fewer than `views` poses) as soon as the live reconstruction's
    recon/live/status.json says "converged": true, after at least `initial_views` poses. Limitation: that flag is
    the plateau test of the live model's last level (600 steps without improvement), which every refit (a quarter
    more views, or 16) starts again: about 100 s of live training between two refits, so the scan ends early only
    when its poses come slowly (a pause, or a pose every 6.5 s or more past 64 views); at the default speed it takes
    all `views` (examples/README.md)."""


@dataclass(frozen=True)
class DaemonConfig:
    """The whole rig config."""

    captures: Path = key(Path("captures"), "path")
    """Captures root: a scan named N is written to <captures>/N/."""
    socket: Path = key(None, "path")
    """Control socket path (mode 0600); default (the same as `spadscan ctl`'s): $SPADSCAN_SOCKET, else
    /tmp/spadscan-<uid>/spadscan.sock (a private 0700 folder, made when the config is read)."""
    auto_resume: bool = key(False, "bool")
    """Resume an interrupted scan by itself at start-up (otherwise it waits, paused, for `ctl resume`); a scan that
    was paused when the daemon stopped (`ctl pause`, a fault) waits either way. A real arm needs its backend's
    confirmation too ([arm] allow_auto_resume for 'ur')."""
    arm: ArmConfig = field(default_factory=ArmConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    scan: ScanConfig = field(default_factory=ScanConfig)
    source: Path | None = None
    """The file this config was read from."""


TABLES = {"arm": ArmConfig, "sensor": SensorConfig, "scan": ScanConfig}
"""The tables of a rig config, by name; everything else at the top level is a key of DaemonConfig."""


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
    top = {k: v for k, v in data.items() if k not in TABLES}
    _check_top_names(top, f"{path}:")
    sections = {}
    for name, cls in TABLES.items():
        table = data.get(name, {})
        if not isinstance(table, dict):
            raise ConfigError(f"{path}: [{name}] must be a table")
        sections[name] = read_section(cls, table, f"{path}: [{name}]", base)
    values = read_values(DaemonConfig, top, f"{path}:", base, skip=(*TABLES, "source"))
    values.setdefault("captures", base / "captures")
    if values.get("socket") is None:
        values["socket"] = Path(default_socket_path())
    cfg = DaemonConfig(**values, **sections, source=path)
    _check_arm(cfg.arm, f"{path}: [arm]")
    _check_arm_chosen(cfg, data.get("arm"), f"{path}:")
    if cfg.auto_resume and not cfg.arm.device.confirms_unattended_resume():
        raise ConfigError(f"{path}: auto_resume = true would let the daemon move the real {cfg.arm.backend!r} arm "
                          f"by itself after a restart, with nobody at the rig: confirm it with [arm] allow_auto_resume "
                          f"= true (a guarded cell only), or leave auto_resume false")
    check_scan(cfg.scan, f"{path}: [scan]")
    _check_paths(cfg, str(path))
    return cfg


def _check_arm_chosen(cfg: DaemonConfig, arm_table: dict | None, where: str) -> None:
    """Refuse a real sensor on an arm nobody chose: without `backend` in [arm] the arm is the simulated default, and
    the captures would pair real histograms with made-up poses. A bench test without an arm says so, writing
    backend = "sim" out."""
    default_sensor = SensorConfig.__dataclass_fields__["backend"].default
    if cfg.sensor.backend == default_sensor or "backend" in (arm_table or {}):
        return
    missing = "no [arm] table" if arm_table is None else "[arm] names no backend"
    raise ConfigError(f"{where} {missing}, so the simulated arm ({cfg.arm.backend!r}, the default) would carry the "
                      f"real {cfg.sensor.backend!r} sensor and its captures would pair real histograms with made-up "
                      f"poses: set [arm] backend = \"ur\" (with its keys), or write [arm] backend = \"sim\" for a "
                      f"bench test without an arm")


def _check_top_names(top: dict, where: str) -> None:
    """Refuse an unknown top-level name in one line. A mistyped table (`[scna]`) holds a table: it is called one and
    the real tables are listed (a list of keys would point away from the fix); an unknown key lists keys and tables."""
    keys = key_names(DaemonConfig, skip=(*TABLES, "source"))
    tables = ", ".join(f"[{t}]" for t in TABLES)
    for name, value in top.items():
        if name in keys:
            continue
        if isinstance(value, dict):
            raise ConfigError(f"{where} unknown table [{name}]{_close(name, TABLES, '[{}]')} (known tables: "
                              f"{tables})")
        if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            raise ConfigError(f"{where} unknown table [[{name}]]{_close(name, TABLES, '[{}]')} (known tables: "
                              f"{tables}, each written once as [name])")
        raise ConfigError(f"{where} unknown key {name!r}{_close(name, keys, '{!r}')} (known keys: {', '.join(keys)}; "
                          f"known tables: {tables})")


def _close(name: str, names, shape: str) -> str:
    """The hint ', did you mean [scan]?' for a name that differs from a known one only in case or by a letter or
    two; empty when none is close."""
    close = difflib.get_close_matches(name.lower(), list(names), n=1, cutoff=0.7)
    return f", did you mean {shape.format(close[0])}?" if close else ""


BACKENDS = {ArmConfig: ARM_BACKENDS, SensorConfig: SENSOR_BACKENDS}
"""The backend registry of each section that has a `backend` key."""


def read_section(cls, table: dict, where: str, base: Path | None = None):
    """Build a section's dataclass from a TOML table; unknown keys and bad values are one-line errors. A section
    with backends reads its common keys, finds the backend by name (once) and reads the rest of the table as that
    backend's keys: a key of another backend, or of none, names the backend chosen."""
    registry = BACKENDS.get(cls)
    if registry is None:
        return cls(**read_values(cls, table, where, base))
    common = set(key_names(cls))
    obj = cls(**read_values(cls, {k: v for k, v in table.items() if k in common}, where, base))
    backend = registry[obj.backend]
    own = {k: v for k, v in table.items() if k not in common}
    try:
        for name in own:
            if name not in key_names(backend):
                raise ConfigError(_not_for_backend(name, obj.backend, registry, key_names(cls)[1:], where))
        device = backend(**read_values(backend, own, where, base)).checked(obj, where, base)
    except ConfigError as exc:
        if "backend" in table:
            raise
        # The user never named the backend this error speaks of (`host` beside a forgotten backend = "ur").
        raise ConfigError(f"{exc} ({_default_taken(obj.backend, registry)})") from None
    return replace(obj, device=device)


def _default_taken(default: str, registry: dict) -> str:
    """Why a backend the user never named is in an error: the table names none, so the default was taken."""
    others = " or ".join(f'"{name}"' for name in registry if name != default)
    return f"no backend is named, so the default {default!r} was taken; set backend = {others} for another"


def _not_for_backend(name: str, chosen: str, registry: dict, common: list[str], where: str) -> str:
    owners = [b for b, cls in registry.items() if name in key_names(cls)]
    if owners:
        return f"{where} {name} applies only to backend {' or '.join(map(repr, owners))}, not {chosen!r}"
    known = ["backend", *common, *key_names(registry[chosen])]
    return f"{where} unknown key {name!r} for backend {chosen!r} (known: {', '.join(known)})"


def scan_with(base: ScanConfig, overrides: dict, where: str = "scan request") -> ScanConfig:
    """The scan config with some keys replaced (from `ctl scan`), validated like the file's [scan] table."""
    scan = replace(base, **read_values(ScanConfig, overrides, where, None))
    check_scan(scan, where)
    return scan


def scan_request(base: ScanConfig, overrides: dict, where: str = "scan request") -> ScanConfig:
    """scan_with for a request (`ctl scan`): also refuses keys that the request sets and its schedule ignores, so
    that `--rings 3` with the Fibonacci schedule is not silently dropped."""
    scan = scan_with(base, overrides, where)
    if "rings" in overrides and scan.schedule != "rings":
        raise ConfigError(f"{where} rings applies only to schedule 'rings', not {scan.schedule!r} (add "
                          f"--schedule rings, or leave --rings out)")
    for name in ADAPTIVE_KEYS:
        if name in overrides and scan.schedule != "adaptive":
            raise ConfigError(f"{where} {name} applies only to schedule 'adaptive', not {scan.schedule!r} (add "
                              f"--schedule adaptive, or leave it out)")
    return scan


ADAPTIVE_KEYS = ("initial_views", "min_view_spacing_deg", "next_views_max_age_s", "next_views_max_lag",
                 "stop_when_converged")
"""[scan] keys that only an adaptive scan reads."""


def scan_to_dict(scan: ScanConfig) -> dict:
    """JSON form of a scan config (stored in the capture's manifest, read back by `scan_from_dict`)."""
    out = {}
    for f in fields(scan):
        v = getattr(scan, f.name)
        out[f.name] = v.tolist() if isinstance(v, np.ndarray) else v
    return out


# ---- cross-key checks --------------------------------------------------------------------------------------------
MIN_LAG = 2
"""The smallest next_views_max_lag that lets a ranking be used: pose i is chosen while pose i - 1 is captured."""


def _check_arm(arm: ArmConfig, where: str) -> None:
    if (arm.workspace_min is None) != (arm.workspace_max is None):
        raise ConfigError(f"{where} workspace_min and workspace_max must be given together")
    if arm.workspace_min is not None and np.any(arm.workspace_min >= arm.workspace_max):
        raise ConfigError(f"{where} workspace_min {arm.workspace_min.tolist()} must be below workspace_max "
                          f"{arm.workspace_max.tolist()} on every axis (m)")
    if arm.max_reach_m is not None and arm.max_reach_m <= arm.min_reach_m:
        raise ConfigError(f"{where} max_reach_m {arm.max_reach_m} must exceed min_reach_m {arm.min_reach_m} (m)")


def check_scan(scan: ScanConfig, where: str) -> None:
    """Cross-key checks of a scan config (elevation order, rings at the poles, chunk size, ranking lag)."""
    single_ring = scan.schedule == "rings" and scan.rings == 1  # its elevation is midway: min = max places it
    if scan.min_elevation_deg > scan.max_elevation_deg or (scan.min_elevation_deg == scan.max_elevation_deg
                                                           and not single_ring):
        raise ConfigError(f"{where} min_elevation_deg {scan.min_elevation_deg:g} must be below max_elevation_deg "
                          f"{scan.max_elevation_deg:g} (degrees; equal only for one ring: schedule 'rings', rings 1)")
    if scan.schedule == "rings":
        _check_ring_poles(scan, where)
    if scan.schedule == "adaptive" and scan.initial_views > scan.views:
        raise ConfigError(f"{where} initial_views {scan.initial_views} exceeds views {scan.views}: an adaptive scan "
                          f"begins with initial_views of its views")
    if scan.schedule == "rings" and scan.views % scan.rings:
        raise ConfigError(f"{where} views {scan.views} must be a multiple of rings {scan.rings}")
    if scan.chunk_size < scan.frames_per_pose:
        raise ConfigError(f"{where} chunk_size {scan.chunk_size} is smaller than frames_per_pose "
                          f"{scan.frames_per_pose}: a pose must fit in one chunk so that it is published whole")
    if scan.next_views_max_lag < MIN_LAG:
        raise ConfigError(f"{where} next_views_max_lag {scan.next_views_max_lag} must be at least {MIN_LAG} (poses): "
                          f"the daemon chooses each pose while the one before it is still being captured, so the "
                          f"freshest ranking is already 1 pose behind and a smaller value makes every ranking stale")


def _check_ring_poles(scan: ScanConfig, where: str) -> None:
    """Refuse a ring of several views at +-90 degrees, as `protocol.schedules.elevation_rings` does, naming the
    config's keys."""
    per_ring = scan.views // scan.rings
    ring = ring_at_pole_deg(scan.rings, per_ring, scan.min_elevation_deg, scan.max_elevation_deg)
    if ring is None:
        return
    if scan.rings == 1:  # min = max = +-90 is the only way to put the midway ring at a pole
        names = "min_elevation_deg and max_elevation_deg"
    else:
        names = "max_elevation_deg" if ring > 0 else "min_elevation_deg"
    raise ConfigError(f"{where} {names} {ring:g}: a ring of {per_ring} views there stands at one viewpoint "
                      f"(straight {'above' if ring > 0 else 'below'} the target); schedule 'rings' needs its "
                      f"rings strictly between -90 and 90 (degrees)")


def _check_paths(cfg: DaemonConfig, where: str) -> None:
    if len(os.fsencode(str(cfg.socket))) > SOCKET_PATH_MAX:
        raise ConfigError(f"{where}: socket path {cfg.socket} is longer than {SOCKET_PATH_MAX} bytes (Unix limit)")
    folder = cfg.socket.parent
    # Tried as the captures root is (`folder_problem`): one the daemon cannot write into passed --check, and the
    # start failed after the devices had connected, with a bare "Permission denied" that named no path.
    problem = not_a_folder(folder) or (None if folder.is_dir() else "no such folder") or folder_problem(folder)
    if problem is not None:
        raise ConfigError(f"{where}: socket folder {folder}: {problem}")
    root = cfg.captures
    if root.exists() and not root.is_dir():
        raise ConfigError(f"{where}: captures {root} exists and is not a folder")
    if not root.exists() and not root.parent.is_dir():  # its parent must exist (examples/README.md)
        raise ConfigError(f"{where}: captures {root}: folder {root.parent} is missing")
    problem = folder_problem(root)  # tried, leaving nothing made: os.access says yes to root where mkdir says no
    if problem is not None:
        raise ConfigError(f"{where}: captures {root}: {problem}")


def check_captures_creatable(root: Path) -> None:
    """Refuse a captures root that start-up could not create or write into (`make_captures`), leaving nothing made,
    as loading the config did (`_check_paths`): asked again when start-up comes, for the folders may have changed."""
    check_folder_option(root, "captures")


def make_captures(root: Path) -> None:
    """Create the captures root (and the folders above it); a failure names the key, as every config error does."""
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"captures {root}: cannot create the folder ({exc.strerror or exc})") from None
