"""Reconstruction configs as dataclasses, and the one registry of presets.

A preset is a function returning a fully resolved `ReconConfig`; the resolved config is saved with every result
(`to_dict`). The presets share every part except the field and its schedule: `field` and `schedule` hold the preset's
own dataclasses, and `model_factory` names the function that builds the preset's model (see `model_api`).
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import math
from dataclasses import dataclass, field
from typing import Any, Callable

from spadscan.protocol.errors import ConfigError

from .errors import ReconstructionError


@dataclass
class RaysConfig:
    """How rays and samples are drawn."""

    rays_per_view: int = 512
    """Rays stratified uniformly in solid angle per view, split evenly over the zones of a multi-zone sensor."""
    importance_rays_per_view: int = 64
    """Extra rays per view drawn where the previous step saw most signal (balance-heuristic weights keep the
    estimate unbiased)."""
    min_rays_per_zone: int = 16
    """Floor on stratified rays per zone when `rays_per_view` is split over many zones."""
    samples_per_ray: int = 256
    """Stratified samples per ray between the ray's entry into and exit from the scene box."""
    importance_samples: int = 32
    """Extra samples per ray drawn from the coarse opacity (inverse-CDF, no gradient)."""
    views_per_batch: int = 2
    """Views rendered per optimisation step."""
    near_m: float = 0.01
    """Samples closer than this to the sensor (metres) are never drawn."""


@dataclass
class LossConfig:
    """What the optimiser minimises."""

    kind: str = "l2"
    """'l2': squared error between measured counts / cycles and predicted detections per cycle (the paper's loss);
    'nll': negative log-likelihood (multinomial with pile-up, or Poisson)."""
    eikonal_weight: float = 0.1
    """Weight of mean (|grad f| - 1)^2."""
    eikonal_points: int = 512
    """Random points in the scene box added to the ray samples for the Eikonal term."""
    tv_weight: float = 0.01
    """Weight of the normal-smoothness (total variation) term; used only where the terms say `tv` (real data)."""


@dataclass
class OptimConfig:
    """Adam with linear warm-up and cosine decay."""

    lr: float = 5e-4
    """Peak learning rate."""
    nominal_steps: int = 300_000
    """Steps the schedule is laid out for when the run gives no step count (the paper's 300K)."""
    warmup_steps: int = 5000
    """Linear warm-up steps (shortened to 2% of the horizon on short runs)."""
    lr_floor: float = 0.05
    """The cosine decays to this fraction of `lr`."""


@dataclass
class SharpnessConfig:
    """Opacity sharpness s of the NeuS-style renderer, in 1 / (scene half-size) units."""

    init: float = 20.0
    """Initial s."""
    learned: bool = True
    """Whether s is optimised (the paper) or fixed."""
    min: float = 1.0
    """Lower clamp."""
    max: float = 1.0e4
    """Upper clamp (the renderer stays finite far past it; see tests)."""
    upsample: float = 64.0
    """Sharpness floor used only to place importance samples."""


@dataclass
class ReconConfig:
    """Everything a reconstruction run needs besides the capture."""

    preset: str
    """Registry name."""
    model_factory: str
    """'module:function' building the model: f(scene: SceneData, config: ReconConfig, device, plan: RunPlan) -> model
    implementing `model_api.ReconModel`."""
    field: Any
    """The preset's field config (a dataclass)."""
    schedule: Any = None
    """The preset's own schedule (a dataclass), or None."""
    rays: RaysConfig = field(default_factory=RaysConfig)
    """Ray and sample counts."""
    loss: LossConfig = field(default_factory=LossConfig)
    """Loss terms and weights."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """Optimiser and learning-rate schedule."""
    sharpness: SharpnessConfig = field(default_factory=SharpnessConfig)
    """Opacity sharpness."""
    default_steps: int | None = None
    """Steps of a run that names neither steps nor a time budget (None: unbounded by steps)."""
    default_budget_s: float | None = None
    """Training seconds of a run that names neither steps nor a time budget (None: unbounded by time)."""
    early_stop: bool = True
    """End a run before its step count or budget once the model reports `converged` (the fast preset's plateau test,
    `schedule.patience_steps`); the paper preset never reports it and runs its whole schedule."""
    albedo_init: float = 1.0
    """Initial (learned) Lambertian albedo of the object; the table has its own."""
    time_oversample: int = 4
    """Fine time cells per bin on which returns are placed before the pulse convolution."""
    mesh_resolution: int = 256
    """Marching-cubes grid cells along the longest side of the scene box for the final mesh."""
    dtype: str = "float32"
    """Tensor dtype of the optimisation ('float32' or 'float64')."""
    metrics_points: int = 300_000
    """Points sampled per mesh for the final metrics (the project's convention: 300,000)."""
    trace_points: int = 30_000
    """Points sampled per mesh for the Chamfer at trace checkpoints (the final metrics use the full count)."""
    trace_checkpoints: int = 12
    """Checkpoints per run at regular training-clock intervals (their evaluation time is not counted)."""
    trace_mesh_resolution: int = 96
    """Marching-cubes resolution of the meshes extracted at checkpoints."""
    unused_sections: tuple[str, ...] = ()
    """Sections this preset never reads (the `fast` preset: rays, optim, sharpness): an override there is refused,
    not silently ignored."""
    unused_fields: tuple[str, ...] = ()
    """Dotted keys of fields this preset never reads (the `fast` preset: dtype, loss.kind): refused likewise."""

    def to_dict(self) -> dict:
        """JSON-able form of the resolved config."""
        return dataclasses.asdict(self)


def parse_override(text: str) -> tuple[str, Any]:
    """'KEY=VALUE' -> (key, value); the value is read as JSON when it parses (numbers, true, null, lists), else
    kept as a string."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise ReconstructionError(f"config override {text!r} must look like KEY=VALUE (e.g. field.resolution=48)")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return key.strip(), value


FIXED_FIELDS = ("preset", "model_factory", "unused_sections", "unused_fields")
"""What makes a preset the preset it is: chosen with --preset, never overridden (a report would name one preset and
run another)."""

CHOICES = {"dtype": ("float32", "float64"), "loss.kind": ("l2", "nll")}
"""The values a text field may take."""


def with_overrides(config: ReconConfig, overrides: dict[str, Any]) -> ReconConfig:
    """A copy of `config` with dotted keys replaced, e.g. {'rays.samples_per_ray': 32, 'field.width': 64}.
    A value must have the type of the field it replaces (ints may stand for floats, lists for tuples) and one of
    CHOICES where it names them; numbers must be finite, and a field whose preset value is positive (counts, sizes,
    weights, rates) takes no negative value. FIXED_FIELDS and what the preset does not read are refused."""
    config = _deep_copy(config)
    for key, value in overrides.items():
        *path, name = key.split(".")
        if key in FIXED_FIELDS:
            raise ReconstructionError(f"config override {key!r}: fixed by the preset (choose the preset with "
                                      f"--preset)")
        if path and path[0] in config.unused_sections:
            raise ReconstructionError(f"config override {key!r}: preset {config.preset!r} does not use the "
                                      f"{path[0]!r} section")
        if key in config.unused_fields:
            raise ReconstructionError(f"config override {key!r}: preset {config.preset!r} does not use it")
        if key in CHOICES and value not in CHOICES[key]:
            raise ReconstructionError(f"config override {key!r}: {value!r} is not one of "
                                      f"{', '.join(CHOICES[key])}")
        obj = config
        for part in path:
            obj = getattr(obj, part, None)
            if obj is None or not dataclasses.is_dataclass(obj):
                raise ReconstructionError(f"config override {key!r}: {part!r} is not a config section")
        field_ = next((f for f in dataclasses.fields(obj) if f.name == name), None)
        if field_ is None:
            raise ReconstructionError(f"config override {key!r}: no field {name!r} in {type(obj).__name__}")
        if dataclasses.is_dataclass(getattr(obj, name)):
            raise ReconstructionError(f"config override {key!r}: a config section; set its fields ({key}.NAME=VALUE)")
        if value is None and "None" not in str(field_.type):
            raise ReconstructionError(f"config override {key!r}: the field takes no null (it holds "
                                      f"{getattr(obj, name)!r})")
        setattr(obj, name, _coerce(getattr(obj, name), value, key))
    return config


def _coerce(old, value, key: str):
    """value, converted to the type of the field's current value `old`; a one-line error when it does not fit."""
    if value is None:
        return value
    if old is None:
        if value is None or (isinstance(value, (int, float)) and not isinstance(value, bool)
                             and math.isfinite(value) and value > 0):
            return value
        # The fields that start as None are optional limits (default_steps, default_budget_s, ...).
        raise ReconstructionError(f"config override {key!r}: {value!r} must be null or a finite number > 0")
    if isinstance(old, bool):
        ok = isinstance(value, bool)
    elif isinstance(old, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(old, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif isinstance(old, tuple):
        ok = isinstance(value, (list, tuple))
        value = tuple(value) if ok else value
    else:
        ok = isinstance(old, str) and isinstance(value, str)
    if not ok:
        raise ReconstructionError(f"config override {key!r}: {value!r} does not fit a field holding {old!r}")
    if isinstance(old, (int, float)) and not isinstance(old, bool):
        if not math.isfinite(value):
            raise ConfigError(f"config override {key!r}: {value!r} must be a finite number")
        if old > 0 and value < 0:
            raise ConfigError(f"config override {key!r}: {value!r} must be >= 0 (the preset's value is {old!r})")
    return value


def _deep_copy(obj):
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.replace(obj, **{f.name: _deep_copy(getattr(obj, f.name)) for f in dataclasses.fields(obj)
                                           if f.init})
    return obj


def _paper() -> ReconConfig:
    from .paper.config import paper_config

    return paper_config()


def _fast() -> ReconConfig:
    try:
        module = importlib.import_module("spadscan.worker.recon.fast.config")
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith("spadscan.worker.recon.fast"):
            raise ReconstructionError("preset 'fast' is not installed (spadscan.worker.recon.fast.config is "
                                      "missing); use --preset paper") from None
        raise
    return module.fast_config()


PRESETS: dict[str, Callable[[], ReconConfig]] = {"paper": _paper, "fast": _fast}
"""Preset name -> function returning its resolved config."""


def preset_config(name: str) -> ReconConfig:
    """The config of preset `name`; a one-line error lists the known names."""
    try:
        make = PRESETS[name]
    except KeyError:
        raise ReconstructionError(f"unknown preset {name!r} (known: {', '.join(PRESETS)})") from None
    return make()


def load_factory(config: ReconConfig) -> Callable:
    """Import the function named by `config.model_factory` ('module:function')."""
    module_name, _, func = config.model_factory.partition(":")
    try:
        return getattr(importlib.import_module(module_name), func)
    except (ImportError, AttributeError) as exc:
        raise ReconstructionError(f"preset {config.preset!r}: cannot load model factory "
                                  f"{config.model_factory!r} ({exc})") from None
