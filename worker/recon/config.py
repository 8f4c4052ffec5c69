"""Reconstruction configs as dataclasses: what every preset's run shares, and `--set KEY=VALUE` overrides.

Each preset's resolved config is its own subclass of `ReconConfig` (`fast.config.FastConfig`,
`paper.config.PaperConfig`) that holds the sections and fields that preset reads, and nothing else: an override of
anything else is refused in one line, never silently ignored. The resolved config is saved with every result
(`to_dict`). Presets are found through `presets.py`, the one registry; `PRESET_NAMES` lists their names for code that
must not import torch (the command line's choices, the worker's queue).
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import dataclass
from operator import attrgetter
from typing import Any, ClassVar

from spadscan.protocol.errors import ConfigError

from .errors import ReconstructionError

PRESET_NAMES = ("paper", "fast")
"""The presets of `presets.PRESETS`, in its order (tests check that the two agree)."""


@dataclass
class ReconConfig:
    """What a run of any preset reads besides its own sections: how long it runs, and how its results are scored."""

    preset: str
    """Registry name (fixed: choose the preset with --preset)."""
    field: Any
    """The preset's field (a dataclass)."""
    schedule: Any
    """The preset's rays, samples and optimiser (a dataclass)."""
    loss: Any
    """The preset's loss weights (a dataclass)."""
    default_steps: int | None = None
    """Steps of a run that names neither steps nor a time budget (None: unbounded by steps)."""
    default_budget_s: float | None = None
    """Training seconds of a run that names neither steps nor a time budget (None: unbounded by time)."""
    early_stop: bool = True
    """End a run before its step count or budget once the model reports `converged`."""
    time_oversample: int = 4
    """Fine time cells per bin on which returns are placed before the pulse convolution."""
    mesh_resolution: int = 256
    """Marching-cubes grid cells along the longest side of the scene box for the final mesh."""
    metrics_points: int = 300_000
    """Points sampled per mesh for the final metrics (the project's convention: 300,000)."""
    trace_points: int = 30_000
    """Points sampled per mesh for the Chamfer at trace checkpoints (the final metrics use the full count)."""
    trace_checkpoints: int = 12
    """Checkpoints per run at regular training-clock intervals (their evaluation time is not counted)."""
    trace_mesh_resolution: int = 96
    """Marching-cubes resolution of the meshes extracted at checkpoints."""

    moved: ClassVar[dict[str, str]] = {}
    """Keys this preset used to have -> where that setting lives now (an override of the old key says so)."""
    inert: ClassVar[tuple[str, ...]] = ()
    """Shared fields this preset's model never reads (the paper's never reports `converged`): refused."""
    choices: ClassVar[dict[str, tuple]] = {}
    """The values a text field may take, by dotted key."""

    def to_dict(self) -> dict:
        """JSON-able form of the resolved config."""
        return dataclasses.asdict(self)

    def tensor_dtype(self) -> str:
        """The dtype the capture's tensors are loaded in: 'float32' (a preset with its own `dtype` says)."""
        return "float32"

    def check(self) -> None:
        """Raise ConfigError (one line, naming the key) for settings no run can use; a preset adds its own checks.
        `with_overrides` calls it, so that a bad value fails before a capture is loaded."""
        for key in ("mesh_resolution", "trace_mesh_resolution"):
            value = getattr(self, key)
            if not 8 <= value <= 1024:
                raise ConfigError(f"{key} {value} must be in [8, 1024] cells")
        # Each of these crashed the run with a traceback once the capture was loaded (the forward model divides by
        # the oversampling and refuses more than 64 cells a bin; the trainer divides the run by the checkpoints; the
        # metrics sample points on the meshes: with none, after the whole run, with no report written).
        check_int("time_oversample", self.time_oversample, 1, 64, hint="fine time cells per bin")
        for key in ("trace_checkpoints", "metrics_points", "trace_points"):
            check_int(key, getattr(self, key), 1)


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


FIXED_FIELDS = ("preset",)
"""What makes a preset the preset it is: chosen with --preset, never overridden (a report would name one preset and
run another)."""


def with_overrides(config: ReconConfig, overrides: dict[str, Any]) -> ReconConfig:
    """A copy of `config` with dotted keys replaced, e.g. {'field.resolution': 48, 'parts.openings.enabled': False}.
    A value must have the type of the field it replaces (ints may stand for floats, lists for tuples) and one of the
    preset's `choices` where it names them; numbers must be finite, and a field whose preset value is positive
    (counts, sizes, weights, rates) takes no negative value. FIXED_FIELDS, keys the preset does not have (or no
    longer has: `moved`) and its `inert` fields are refused; so is a result that the preset's `check` refuses. A value
    that those generic rules refuse is refused in the words of the preset's `check` where it checks the field itself
    (its message states the field's whole range, which the generic rules do not know)."""
    preset_config, config = config, _deep_copy(config)
    for key, value in overrides.items():
        _set(config, key, value, preset_config)
    config.check()
    return config


def _set(config: ReconConfig, key: str, value, preset_config: ReconConfig) -> None:
    """Set `key` of `config` (the preset's, `preset_config`, with the overrides before this one) to `value`."""
    *path, name = key.split(".")
    preset = config.preset
    if key in FIXED_FIELDS:
        raise ReconstructionError(f"config override {key!r}: fixed by the preset (choose the preset with --preset)")
    if key in config.moved:
        raise ReconstructionError(f"config override {key!r}: preset {preset!r} has moved it: {config.moved[key]}")
    if key in config.inert:
        raise ReconstructionError(f"config override {key!r}: preset {preset!r} does not use it")
    if key in config.choices and value not in config.choices[key]:
        raise ReconstructionError(f"config override {key!r}: {value!r} is not one of {', '.join(config.choices[key])}")
    obj = config
    for i, part in enumerate(path):
        inner = getattr(obj, part, None)
        if inner is None or not dataclasses.is_dataclass(inner):
            where = ".".join(path[:i]) or f"preset {preset!r}"
            raise ReconstructionError(f"config override {key!r}: {where} has no section {part!r} (its sections: "
                                      f"{', '.join(_sections(obj))})")
        obj = inner
    field_ = next((f for f in dataclasses.fields(obj) if f.name == name), None)
    if field_ is None:
        where = ".".join(path) or f"preset {preset!r}"
        raise ReconstructionError(f"config override {key!r}: no field {name!r} in {type(obj).__name__} ({where}); "
                                  f"preset {preset!r} does not use it")
    if dataclasses.is_dataclass(getattr(obj, name)):
        raise ReconstructionError(f"config override {key!r}: a config section; set its fields ({key}.NAME=VALUE)")
    if value is None and "None" not in str(field_.type):
        raise ReconstructionError(f"config override {key!r}: the field takes no null (it holds "
                                  f"{getattr(obj, name)!r})")
    old = getattr(obj, name)
    try:
        new = _coerce(old, value, key)
    except ConfigError as generic:
        raise (_in_own_words((config, preset_config), key, value, old) or generic) from None
    setattr(obj, name, new)


def _in_own_words(configs: tuple[ReconConfig, ...], key: str, value, old) -> ConfigError | None:
    """A value the generic rules refuse, refused in the words of the preset's own check of `key`, which states the
    field's whole range (the generic rules know only the type and the sign of the preset's value): so every value
    out of a field's range gets one message. None where the preset does not check `key` itself. `configs`: the
    config with the overrides so far, then the preset's own (where an earlier override is refused first)."""
    if isinstance(old, tuple):
        return None  # a list's check reads its items: a value that is no list is the generic rule's to refuse
    own = _own_refusal(configs, key, value)
    if own is not None or not _is_number(old):
        return own
    # The check lets the value through (inf where it asks for > 0, 3.5 where it asks for >= 1) or cannot compare it
    # ('abc'): the generic rule it breaks, then the field's range, as the check states it for a value in no range.
    rule = _own_refusal(configs, key, -math.inf)
    if rule is None:
        return None
    kind = _kind(old)
    subject = f"{key} {-math.inf!r} "
    text = str(rule)
    if text.startswith(f"{subject}must be {kind}"):
        return ConfigError(f"{key} {value!r} {text[len(subject):]}")
    return ConfigError(f"{key} {value!r} must be {kind}, and {text.removeprefix(subject)}")


def _own_refusal(configs: tuple[ReconConfig, ...], key: str, value) -> ConfigError | None:
    """The error the preset's `check` raises about `key` once it holds `value`, in the first of `configs` where the
    check reaches `key`; None where it accepts the value or has no check of `key` of its own."""
    *path, name = key.split(".")
    for config in configs:
        trial = _deep_copy(config)
        setattr(attrgetter(".".join(path))(trial) if path else trial, name, value)
        try:
            trial.check()
        except ConfigError as exc:
            if _names(str(exc), key):
                return exc
            continue  # it refused another field first: an earlier override, or (in the preset's config) none
        except (TypeError, ValueError, ArithmeticError):
            return None  # a value of another type trips a check written for the field's own type
        return None
    return None


def _names(message: str, key: str) -> bool:
    """Whether a check's message is about `key`: it starts with it, or names the field among others of its section
    before it says what they must be ('parts.openings.passes, patience, min_flagged and min_hits must be >= 1')."""
    if message.startswith(f"{key} "):
        return True
    section, _, name = key.rpartition(".")
    subject = message.partition(" must ")[0]
    named = re.search(rf"\b{re.escape(name)}\b", subject) is not None
    return bool(section) and subject.startswith(f"{section}.") and named


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _sections(obj) -> list[str]:
    return [f.name for f in dataclasses.fields(obj) if dataclasses.is_dataclass(getattr(obj, f.name))]


def _coerce(old, value, key: str):
    """value, converted to the type of the field's current value `old`; a one-line error when it does not fit."""
    if value is None:
        return value
    if old is None:
        if _is_number(value) and _finite(value) and value > 0:
            return value
        # The fields that start as None are optional limits (default_steps, default_budget_s, ...).
        raise ConfigError(f"config override {key!r}: {value!r} must be null or a finite number > 0")
    fits, new = _converted(old, value)
    if not fits:
        raise ConfigError(f"config override {key!r}: {value!r} must be {_generic_rule(old)} (the preset's value is "
                          f"{old!r})")
    return new


def _converted(old, value) -> tuple[bool, Any]:
    """(whether `value` fits a field holding `old` by the generic rules, `value` in the field's type)."""
    if isinstance(old, bool):
        return isinstance(value, bool), value
    if isinstance(old, (int, float)):
        if not (_is_number(value) and (isinstance(value, int) or isinstance(old, float))):
            return False, value
        try:
            new = type(old)(value)
        except OverflowError:  # an integer too large for a float
            return False, value
        return _finite(new) and not (old > 0 and new < 0), new
    if isinstance(old, tuple):
        ok = isinstance(value, (list, tuple))
        return ok, (tuple(value) if ok else value)
    return isinstance(old, str) and isinstance(value, str), value


def _finite(number) -> bool:
    """Whether `number` is finite: every int is (math.isfinite converts it to a float, which an int over 1e308 does
    not fit)."""
    return isinstance(number, int) or math.isfinite(number)


def _generic_rule(old) -> str:
    """What the generic rules let a field holding `old` take, as a message says it."""
    if isinstance(old, bool):
        return "true or false"
    if isinstance(old, (int, float)):
        return f"{_kind(old)} >= 0" if old > 0 else _kind(old)
    return "a list" if isinstance(old, tuple) else "text"


def _kind(old: int | float) -> str:
    """The numbers a field holding the number `old` takes (an int field takes no 3.5, nor 1e9: JSON reads a float)."""
    return "an integer" if isinstance(old, int) else "a finite number"


def check_in_range(key: str, value, lo: float, hi: float, unit: str = "metres", hint: str = "") -> None:
    """Raise ConfigError naming `key` unless `value` is a number (not a bool) in [lo, hi]; NaN is refused too (every
    comparison with it is false). `hint`, when given, follows in brackets: what the bounds mean."""
    if not (isinstance(value, (int, float)) and not isinstance(value, bool) and lo <= value <= hi):
        raise ConfigError(f"{key} {value!r} must be in [{lo:g}, {hi:g}] {unit}" + (f" ({hint})" if hint else ""))


def check_int(key: str, value, lo: int, hi: int | None = None, hint: str = "") -> None:
    """Raise ConfigError naming `key` unless `value` is an integer (not a bool) >= lo, and <= hi where given.
    `hint`, when given, follows in brackets: what the bounds mean."""
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= lo and (hi is None or value <= hi)):
        bounds = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ConfigError(f"{key} {value!r} must be an integer {bounds}" + (f" ({hint})" if hint else ""))


def _deep_copy(obj):
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.replace(obj, **{f.name: _deep_copy(getattr(obj, f.name)) for f in dataclasses.fields(obj)
                                           if f.init})
    return obj


__all__ = ["PRESET_NAMES", "ReconConfig", "parse_override", "with_overrides", "FIXED_FIELDS", "check_in_range",
           "check_int"]
