"""Reading a sweep file (TOML): the scenes, the base condition, the grids, the methods and the metrics.

    [sweep]
    scenes = ["builtin:sphere"]   # mesh files (relative to this file), builtin:NAME, or lcspc:NAME (--lcspc DIR)
    mode = "one-at-a-time"        # each grid axis varied alone around the base (the paper's design), or "product"
    presets = ["fast"]            # reconstruction presets run at every point ("fast", "paper")
    baselines = ["reprojection", "space-carving"]

    [base]                        # the base condition; every key has a default (see params.py)
    sensor = "lcspc-sim"
    views = 256

    [grid]                        # the values each axis takes; no [grid] (or an empty one): the base condition
    views = [16, 64, 256]         # alone, one point per scene (sweep-plot: each method's Chamfer there)

    [fast]                        # per preset: steps and/or budget_s, and config overrides
    steps = 3000
    set = { "field.resolution" = 64 }

    [baselines]                   # the threshold grid calibrated against the ground truth, space carving's voxels
    thresholds = [3, 5, 10, 20, 50, 100, 300]
    resolution = 128

    [metrics]
    points = 300000               # samples per mesh for the final metrics
    calibration_points = 100000   # samples per mesh while a baseline's threshold is calibrated

Every problem is a one-line ConfigError naming the file and the key.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from spadscan.protocol.errors import ConfigError, SpadscanError
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.presets import preset_config

from .params import PARAMS, RINGS_ELEVATIONS, bin_ps_of, check_value, defaults_for

MODES = ("one-at-a-time", "product")
PRESETS = ("fast", "paper")
BASELINES = ("reprojection", "space-carving")
DEFAULT_RINGS = 4
DEFAULT_METRICS_POINTS = 300_000
DEFAULT_CALIBRATION_POINTS = 100_000
MAX_POINTS_PER_SWEEP = 100_000
TABLES = {
    "sweep": ("scenes", "mode", "presets", "baselines"),
    "base": tuple(PARAMS),
    "grid": tuple(name for name, p in PARAMS.items() if p.axis),
    "fast": ("steps", "budget_s", "set"),
    "paper": ("steps", "budget_s", "set"),
    "baselines": ("thresholds", "resolution"),
    "metrics": ("points", "calibration_points"),
}


@dataclass(frozen=True)
class PresetRun:
    """How one reconstruction preset runs at every point: a step count and/or a time budget (neither: the
    preset's default), and config overrides (dotted keys, as `spadscan reconstruct --set`)."""

    name: str
    steps: int | None = None
    budget_s: float | None = None
    overrides: dict = field(default_factory=dict)

    def record(self) -> dict:
        return {"steps": self.steps, "budget_s": self.budget_s, "set": dict(sorted(self.overrides.items()))}


@dataclass(frozen=True)
class BaselineRun:
    """The baselines run at every point, each with its threshold calibrated over `thresholds` (noise standard
    deviations) against the ground truth; space carving on a grid of `resolution` voxels a side."""

    methods: tuple[str, ...]
    thresholds: tuple[float, ...] | None = None
    """None: the baselines' own calibration grid."""
    resolution: int = 128

    def record(self) -> dict:
        return {"methods": list(self.methods), "thresholds": None if self.thresholds is None else
                list(self.thresholds), "resolution": self.resolution}


@dataclass(frozen=True)
class SweepSpec:
    """A sweep file, checked and resolved: `base` holds every parameter (defaults filled in from the sensor
    preset); `grid` maps each axis to its values, in the file's order."""

    path: Path
    text: str
    scenes: tuple[str, ...]
    mode: str
    base: dict
    grid: dict
    presets: tuple[PresetRun, ...]
    baselines: BaselineRun
    metrics_points: int = DEFAULT_METRICS_POINTS
    calibration_points: int = DEFAULT_CALIBRATION_POINTS

    @property
    def methods(self) -> tuple[str, ...]:
        """Every method a point runs, presets first."""
        return tuple(p.name for p in self.presets) + self.baselines.methods

    def method_record(self) -> dict:
        """What the methods' results depend on (part of every point's id)."""
        return {"presets": {p.name: p.record() for p in self.presets}, "baselines": self.baselines.record(),
                "metrics": {"points": self.metrics_points, "calibration_points": self.calibration_points}}


def load_spec(path) -> SweepSpec:
    """Read and check the sweep file at `path`."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such sweep file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the sweep file ({' '.join(str(exc).split())})") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return parse_spec(raw, path, text)


def parse_spec(raw: dict, path: Path, text: str = "") -> SweepSpec:
    """A SweepSpec from the parsed TOML `raw` of the file at `path` (named in every error)."""
    where = str(path)
    for key, value in raw.items():
        if key not in TABLES:
            raise ConfigError(f"{where}: unknown table [{key}] (known: {', '.join(TABLES)})")
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: {key} must be a table ([{key}])")
        for sub in value:
            if sub not in TABLES[key]:
                raise ConfigError(f"{where}: [{key}] has no key {sub!r} (known: {', '.join(TABLES[key])})")
    top = raw.get("sweep", {})
    scenes = _str_list(top.get("scenes"), f"{where}: [sweep] scenes", allow_empty=False)
    if len(set(scenes)) != len(scenes):
        raise ConfigError(f"{where}: [sweep] scenes names a scene twice")
    mode = top.get("mode", "one-at-a-time")
    if mode not in MODES:
        raise ConfigError(f"{where}: [sweep] mode = {mode!r} is not one of {', '.join(MODES)}")
    preset_names = _str_list(top.get("presets", ["fast"]), f"{where}: [sweep] presets", choices=PRESETS)
    baseline_names = _str_list(top.get("baselines", list(BASELINES)), f"{where}: [sweep] baselines",
                               choices=BASELINES)
    if not preset_names and not baseline_names:
        raise ConfigError(f"{where}: [sweep] names no preset and no baseline: nothing to run at a point")
    for name in PRESETS:
        if name in raw and name not in preset_names:
            raise ConfigError(f"{where}: [{name}] configures a preset that [sweep] presets does not run")
    if "baselines" in raw and not baseline_names:
        raise ConfigError(f"{where}: [baselines] configures baselines that [sweep] baselines does not run")
    base = _base(raw.get("base", {}), where)
    grid = _grid(raw.get("grid", {}), base, where)
    presets = tuple(_preset(name, raw.get(name, {}), where) for name in preset_names)
    baselines = _baselines(baseline_names, raw.get("baselines", {}), where)
    metrics = raw.get("metrics", {})
    points = _count(metrics.get("points", DEFAULT_METRICS_POINTS), f"{where}: [metrics] points", 1000, 10_000_000)
    calibration = _count(metrics.get("calibration_points", DEFAULT_CALIBRATION_POINTS),
                         f"{where}: [metrics] calibration_points", 1000, 10_000_000)
    spec = SweepSpec(Path(path), text, tuple(scenes), mode, base, grid, presets, baselines, points, calibration)
    n = count_points(spec)
    if n > MAX_POINTS_PER_SWEEP:
        raise ConfigError(f"{where}: {n:,} points (over {MAX_POINTS_PER_SWEEP:,}); a product of these grids is "
                          f"more than any cluster should be asked for")
    return spec


def count_points(spec: SweepSpec) -> int:
    """Grid entries per scene times scenes (before points that coincide are merged)."""
    sizes = [len(v) for v in spec.grid.values()]
    per_scene = (sum(sizes) if spec.mode == "one-at-a-time" else math.prod(sizes)) if sizes else 1
    return per_scene * len(spec.scenes)


def _base(table: dict, where: str) -> dict:
    sensor_name = check_value("sensor", table.get("sensor", "lcspc-sim"), f"{where}: [base]")
    try:
        sensor = sensor_preset(sensor_name)
    except SpadscanError as exc:
        raise ConfigError(f"{where}: [base] {exc}") from None
    base = {"sensor": sensor_name, **defaults_for(sensor)}
    for key, value in table.items():
        if key != "sensor":
            base[key] = check_value(key, value, f"{where}: [base]")
    if base["schedule"] == "rings":
        if base["rings"] is None:
            base["rings"] = DEFAULT_RINGS
        for key, value in RINGS_ELEVATIONS.items():  # the spiral's band would stack a ring at the zenith
            if key not in table:
                base[key] = value
    if base["ambient"] is None:
        # The preset's background per bin, scaled to the base condition's bins (the flux in time is the scene's).
        base["ambient"] = sensor.background * base["bin_ps"] / bin_ps_of(sensor)
    return base


def _grid(table: dict, base: dict, where: str) -> dict:
    grid = {}
    for axis, values in table.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{where}: [grid] {axis} must be a non-empty list of values")
        checked = [check_value(axis, v, f"{where}: [grid] {axis}") for v in values]
        if len(set(checked)) != len(checked):
            raise ConfigError(f"{where}: [grid] {axis} lists a value twice")
        if axis == "rings" and base["schedule"] != "rings":
            raise ConfigError(f"{where}: [grid] rings varies the rings of schedule = 'rings', not of "
                              f"{base['schedule']!r}")
        grid[axis] = checked
    return grid


def _preset(name: str, table: dict, where: str) -> PresetRun:
    steps = table.get("steps")
    if steps is not None:
        steps = _count(steps, f"{where}: [{name}] steps", 1, 10**9)
    budget = table.get("budget_s")
    if budget is not None and not (isinstance(budget, (int, float)) and not isinstance(budget, bool)
                                   and math.isfinite(budget) and budget > 0):
        raise ConfigError(f"{where}: [{name}] budget_s = {budget!r} must be a positive number of seconds")
    overrides = table.get("set", {})
    if not isinstance(overrides, dict):
        raise ConfigError(f"{where}: [{name}] set must be a table of config keys, e.g. "
                          f"set = {{ \"field.resolution\" = 48 }}")
    overrides = _flatten(overrides)
    if "metrics_points" in overrides:
        raise ConfigError(f"{where}: [{name}] set: metrics_points is [metrics] points (every method is scored alike)")
    # Check the overrides against the preset's config now, not on a worker hours later.
    try:
        with_overrides(preset_config(name), overrides)
    except SpadscanError as exc:
        raise ConfigError(f"{where}: [{name}] set: {exc}") from None
    return PresetRun(name, steps, None if budget is None else float(budget), overrides)


def _flatten(table: dict, prefix: str = "") -> dict:
    """{"field": {"resolution": 48}} and {"field.resolution": 48} both as {"field.resolution": 48}."""
    flat = {}
    for key, value in table.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _baselines(names: list[str], table: dict, where: str) -> BaselineRun:
    thresholds = table.get("thresholds")
    if thresholds is not None:
        if not (isinstance(thresholds, list) and thresholds and all(
                isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) and t > 0
                for t in thresholds)):
            raise ConfigError(f"{where}: [baselines] thresholds must be a non-empty list of numbers > 0 (noise "
                              f"standard deviations)")
        thresholds = tuple(sorted({float(t) for t in thresholds}))
    resolution = _count(table.get("resolution", 128), f"{where}: [baselines] resolution", 8, 512)
    return BaselineRun(tuple(names), thresholds, resolution)


def _count(value, what: str, lo: int, hi: int) -> int:
    if not (isinstance(value, int) and not isinstance(value, bool) and lo <= value <= hi):
        raise ConfigError(f"{what} = {value!r} must be a whole number in [{lo:,}, {hi:,}]")
    return value


def _str_list(value, what: str, *, choices=None, allow_empty: bool = True) -> list[str]:
    if value is None:
        raise ConfigError(f"{what} is missing")
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ConfigError(f"{what} must be a list of strings")
    if not value and not allow_empty:
        raise ConfigError(f"{what} is empty")
    if choices is not None:
        for v in value:
            if v not in choices:
                raise ConfigError(f"{what}: {v!r} is not one of {', '.join(choices)}")
        if len(set(value)) != len(value):
            raise ConfigError(f"{what} names one twice")
    return list(value)


__all__ = ["SweepSpec", "PresetRun", "BaselineRun", "load_spec", "parse_spec", "count_points", "MODES",
           "PRESETS", "BASELINES"]
