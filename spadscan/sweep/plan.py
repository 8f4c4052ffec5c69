"""A sweep file expanded into grid entries and the points that run them, each with a stable id.

A point is one simulate -> reconstruct -> baselines -> metrics run: a scene and every imaging parameter resolved.
Its id is a hash of everything its results depend on (the scene's label and mesh digest, every parameter, the
point's sensor model and photon settings, the methods and how they are run and scored), so the same point has the
same id in every run of every sweep file that asks for it, and grid entries that coincide (the base condition sits
on every axis) share one point. What the file leaves to spadscan (a preset's defaults, the baselines' default
thresholds, the code's version) and the device are not in the id: each method's own fingerprint (fingerprint.py),
stored with the point, holds them, and a stored method whose fingerprint differs runs again. The plan's
*fingerprint* hashes the base condition and the methods: a results folder holds the points of one fingerprint only,
so that a changed base condition never mixes with results of the old one.
"""

from __future__ import annotations

import hashlib
import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path

from spadscan.protocol.errors import ConfigError

from .params import check_point, shown
from .scenes import Scene, load_scene
from .spec import BaselineRun, PresetRun, SweepSpec

FORMAT = 2
"""Version of the point record; a new one changes every id. 2: the record holds the simulator's photon settings."""
PRODUCT_AXIS = "product"
"""The `axis` of an entry of a product grid (every axis varies at once)."""


@dataclass(frozen=True)
class Entry:
    """One grid entry: on `axis` (or PRODUCT_AXIS) the value `value` (None for a product), run by a point."""

    scene: str
    axis: str
    value: object
    point_id: str


@dataclass(frozen=True)
class PointTask:
    """Everything a worker needs to run one point."""

    id: str
    scene: Scene
    params: dict
    record: dict
    """What the id is the hash of (stored with the result)."""
    presets: tuple[PresetRun, ...]
    baselines: BaselineRun
    metrics_points: int
    calibration_points: int
    base_bin_ps: float
    """The base condition's bin size, to which `ambient` refers."""

    def describe(self, base: dict | None = None) -> str:
        """A short name for messages: the scene and the parameters that differ from `base` (all varied axes of a
        one-at-a-time sweep are one of them)."""
        changed = [k for k, v in self.params.items() if base is not None and base.get(k) != v]
        parts = [f"{k}={shown(self.params[k])}" for k in changed]
        return " ".join([self.scene.label, *(parts or ["(base condition)"])])


@dataclass
class Plan:
    spec: SweepSpec
    scenes: tuple[Scene, ...]
    entries: list[Entry]
    points: dict[str, PointTask] = field(default_factory=dict)
    base_record: dict = field(default_factory=dict)
    fingerprint: str = ""


def canonical_hash(data) -> str:
    """sha256 of the canonical JSON of `data` (sorted keys, no spaces)."""
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


def make_plan(spec: SweepSpec, lcspc_root: Path | None = None) -> Plan:
    """Resolve the scenes (each mesh is loaded once for its digest), expand the grids and check every point."""
    sweep_dir = spec.path.resolve().parent
    scenes = tuple(load_scene(label, sweep_dir, lcspc_root) for label in spec.scenes)
    methods = spec.method_record()
    base_record = {"format": FORMAT, "base": spec.base, **methods}
    plan = Plan(spec, scenes, [], {}, base_record, canonical_hash(base_record)[:16])
    checked: dict[str, dict] = {}  # one check per distinct parameter set
    # The base condition first: a fault in [base] is in every entry, and blaming the first one misleads.
    try:
        checked[canonical_hash(dict(spec.base))] = check_point(dict(spec.base), spec.base["bin_ps"])
    except ConfigError as exc:
        raise ConfigError(f"{spec.path}: [base] (the base condition): {exc}") from None
    for scene in scenes:
        for axis, value, params in _grid_points(spec):
            key = canonical_hash(params)
            if key not in checked:
                try:
                    checked[key] = check_point(params, spec.base["bin_ps"])
                except ConfigError as exc:
                    at = "the base condition" if axis == "base" else (
                        f"[grid] {axis} = {shown(value)}" if axis != PRODUCT_AXIS else
                        "[grid] " + ", ".join(f"{a} = {shown(params[a])}" for a in spec.grid))
                    raise ConfigError(f"{spec.path}: {at}: {exc}") from None
            record = {"format": FORMAT, "scene": scene.record(), "params": params, **checked[key], **methods}
            pid = canonical_hash(record)[:16]
            if pid not in plan.points:
                plan.points[pid] = PointTask(pid, scene, params, record, spec.presets, spec.baselines,
                                             spec.metrics_points, spec.calibration_points, spec.base["bin_ps"])
            plan.entries.append(Entry(scene.label, axis, value, pid))
    return plan


def _grid_points(spec: SweepSpec):
    """(axis, value, params) for each grid entry of one scene; the base condition alone when the grid is empty."""
    if not spec.grid:
        yield "base", None, dict(spec.base)
        return
    if spec.mode == "one-at-a-time":
        for axis, values in spec.grid.items():
            for value in values:
                yield axis, value, {**spec.base, axis: value}
        return
    axes = list(spec.grid)
    for combo in itertools.product(*(spec.grid[a] for a in axes)):
        yield PRODUCT_AXIS, None, {**spec.base, **dict(zip(axes, combo))}



__all__ = ["Plan", "PointTask", "Entry", "make_plan", "canonical_hash", "FORMAT", "PRODUCT_AXIS"]
