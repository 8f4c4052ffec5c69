"""How a config key is declared and read: a dataclass field carries its `Key` (kind, range, unit), and `read_values`
turns a TOML table into checked values. Shared by the rig config (`config.py`) and every backend's own settings
(`backends/`), so that a key reads and fails the same way wherever it is declared.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from spadscan.protocol.errors import ConfigError


@dataclass(frozen=True)
class Key:
    """How one config key is read: its kind, its range (lo/hi; open bounds when lo_open/hi_open), its unit."""

    kind: str  # str, float, int, bool, path, vec3, mat4, choice, ints
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple = ()
    unit: str = ""


def key(default, kind: str, **spec):
    """A dataclass field that carries its Key spec (mutable defaults become factories)."""
    if isinstance(default, (list, np.ndarray)):
        return field(default_factory=lambda: np.array(default, dtype=float), metadata={"key": Key(kind, **spec)})
    return field(default=default, metadata={"key": Key(kind, **spec)})


def key_names(cls, skip=()) -> list[str]:
    """The config keys a dataclass declares (fields that carry a Key), in declaration order."""
    return [f.name for f in fields(cls) if "key" in f.metadata and f.name not in skip]


def key_spec(cls, name: str) -> Key:
    """The Key of field `name` of a config dataclass."""
    return next(f.metadata["key"] for f in fields(cls) if f.name == name)


def read_values(cls, table: dict, where: str, base: Path | None, skip=()) -> dict:
    """Checked values of a TOML table for config dataclass `cls`; an unknown key is a one-line ConfigError."""
    known = {f.name: f for f in fields(cls) if "key" in f.metadata and f.name not in skip}
    values = {}
    for name, value in table.items():
        if name not in known:
            raise ConfigError(f"{where} unknown key {name!r} (known: {', '.join(known)})")
        values[name] = coerce(value, known[name].metadata["key"], f"{where} {name}", base)
    return values


def coerce(value, spec: Key, where: str, base: Path | None):
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
        arr[:3, :3] = nearest_rotation(arr[:3, :3])
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


def nearest_rotation(r: np.ndarray) -> np.ndarray:
    """The rotation nearest to r (3, 3) (its polar factor). A transform typed with four decimals is rigid to 1e-4,
    which the config accepts, but the arm's pose conversion refuses rotations off by more than 1e-6: every target
    planned through it would be refused."""
    u, _, vt = np.linalg.svd(r)
    return u @ vt


def _check_rigid(m: np.ndarray, where: str) -> None:
    r = m[:3, :3]
    if (np.abs(r @ r.T - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(r) - 1) > 1e-4
            or np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9):
        raise ConfigError(f"{where} is not a rigid transform (rotation must be orthonormal with det +1, last row "
                          f"[0, 0, 0, 1]; translation in metres)")
    if np.abs(m[:3, 3]).max() > 1.0:
        raise ConfigError(f"{where} translation {m[:3, 3].tolist()} exceeds 1 m: give it in metres")
