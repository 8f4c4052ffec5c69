"""Reading a sweep folder back for plots and pages: its grid (sweep.json) and its rows (results.csv)."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

from spadscan.protocol.errors import ConfigError

from .store import RESULTS_CSV, SWEEP_JSON, column_name


@dataclass(frozen=True)
class SweepResults:
    folder: Path
    mode: str
    grid: dict
    """axis -> values, in the sweep file's order."""
    base: dict
    scenes: list
    methods: list
    presets: list
    rows: list
    """results.csv as dicts (strings)."""

    def method_value(self, row: dict, method: str, key: str = "chamfer_mm") -> float | None:
        """A method's number in a row, or None when it has none (failed, not run)."""
        return number(row.get(f"{column_name(method)}_{key}"))

    def method_failed(self, row: dict, method: str) -> bool:
        """True where the method did not give a result at that point (it failed, or the point failed first)."""
        return row.get(f"{column_name(method)}_status") != "done"


def number(text) -> float | None:
    try:
        v = float(text)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def read_results(folder) -> SweepResults:
    """The sweep in `folder`; a one-line ConfigError when it is not a sweep folder or has no results yet."""
    folder = Path(folder)
    meta_path = folder / SWEEP_JSON
    if not folder.is_dir():
        raise ConfigError(f"{folder}: no such sweep folder")
    try:
        meta = json.loads(meta_path.read_text())
        grid, mode = meta["grid"], meta["mode"]
    except FileNotFoundError:
        raise ConfigError(f"{folder}: holds no {SWEEP_JSON}; is it the --out of a `spadscan sweep`?") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{meta_path}: unreadable ({' '.join(str(exc).split())})") from None
    try:
        with open(folder / RESULTS_CSV, newline="") as f:
            rows = list(csv.DictReader(f))
    except FileNotFoundError:
        raise ConfigError(f"{folder}: holds no {RESULTS_CSV} yet (no point has finished)") from None
    except (OSError, csv.Error, UnicodeDecodeError) as exc:
        raise ConfigError(f"{folder / RESULTS_CSV}: unreadable ({' '.join(str(exc).split())})") from None
    if not rows:
        raise ConfigError(f"{folder / RESULTS_CSV}: no point has finished yet")
    return SweepResults(folder, mode, grid, meta.get("base", {}), meta.get("scenes", []), meta.get("methods", []),
                        meta.get("presets", []), rows)


__all__ = ["SweepResults", "read_results", "number"]
