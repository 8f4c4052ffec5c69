"""Reading a sweep folder back for plots and pages: its grid (sweep.json) and its rows (results.csv)."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

from spadscan.protocol.errors import ConfigError

from .store import RESULTS_CSV, SWEEP_JSON, WARNINGS_JOIN, column_name

NOT_CONVERGED = "the run did not converge"


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

    def method_warnings(self, row: dict, method: str) -> list[str]:
        """The warnings of a method that gave a result at that point (results.csv's <method>_warnings), with "the run
        did not converge" for a preset that did not and says nothing else; [] for none, or a failed method."""
        if self.method_failed(row, method):
            return []
        text = row.get(f"{column_name(method)}_warnings") or ""
        lines = [w.strip() for w in text.split(WARNINGS_JOIN) if w.strip()]
        if not lines and row.get(f"{column_name(method)}_converged") == "False":
            lines = [NOT_CONVERGED]
        return lines

    def threshold_edge(self, row: dict, method: str) -> str:
        """'lowest', 'highest' or 'only' where a baseline's calibrated threshold is at an end of those tried; ''."""
        return "" if self.method_failed(row, method) else row.get(f"{column_name(method)}_threshold_edge") or ""


def value_key(text) -> tuple:
    """A sort key of a results cell's value: numbers by value, before any text, which sorts as text."""
    v = number(text)
    return (0, v, "") if v is not None else (1, 0.0, str(text))


def number(text) -> float | None:
    try:
        v = float(text)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


ROW_COLUMNS = ("scene", "axis", "value", "point", "status", "reason")
"""The columns of results.csv that the plot and the page cannot do without."""


def read_results(folder) -> SweepResults:
    """The sweep in `folder`; a one-line ConfigError when it is not a sweep folder, has no results yet, or its files
    are not the shape `spadscan sweep` writes."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(f"{folder}: no such sweep folder" + (" (a file, not a folder)" if folder.exists() else ""))
    meta = _read_meta(folder)
    rows = _read_rows(folder / RESULTS_CSV)
    return SweepResults(folder, meta["mode"], meta["grid"], meta.get("base", {}), meta.get("scenes", []),
                        meta.get("methods", []), meta.get("presets", []), rows)


def _read_meta(folder: Path) -> dict:
    """sweep.json, checked for the shapes the plot relies on."""
    path = folder / SWEEP_JSON
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{folder}: holds no {SWEEP_JSON}; is it the --out of a `spadscan sweep`?") from None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: unreadable ({' '.join(str(exc).split())})") from None
    problem = _meta_problem(meta)
    if problem:
        raise ConfigError(f"{path}: unreadable ({problem}); is it the --out of a `spadscan sweep`?")
    return meta


def _meta_problem(meta) -> str | None:
    """What is wrong with a sweep.json's shape, or None."""
    if not isinstance(meta, dict):
        return "not a JSON object"
    if not isinstance(meta.get("mode"), str):
        return "'mode' is not a string"
    grid = meta.get("grid")
    if not isinstance(grid, dict) or not all(isinstance(v, list) for v in grid.values()):
        return "'grid' is not an object of parameter -> list of values"
    for key, kind, name in (("base", dict, "an object"), ("scenes", list, "a list"), ("methods", list, "a list"),
                            ("presets", list, "a list")):
        if not isinstance(meta.get(key, kind()), kind):
            return f"{key!r} is not {name}"
    if not all(isinstance(v, str) for key in ("scenes", "methods", "presets") for v in meta.get(key, [])):
        return "'scenes', 'methods' and 'presets' must hold names"
    return None


def _read_rows(path: Path) -> list[dict]:
    """results.csv as dicts of strings. utf-8-sig: a spreadsheet that re-saves the file may put a byte-order mark
    before the first column's name."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f, restval="")  # a short row's missing cells read as empty, not None
            rows = list(reader)
            header = reader.fieldnames or []
    except FileNotFoundError:
        raise ConfigError(f"{path.parent}: holds no {RESULTS_CSV} yet (no point has finished)") from None
    except (OSError, csv.Error, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: unreadable ({' '.join(str(exc).split())})") from None
    if not rows:
        raise ConfigError(f"{path}: no point has finished yet")
    missing = [c for c in ROW_COLUMNS if c not in header]
    if missing:
        raise ConfigError(f"{path}: not a sweep's results table: it lacks the column{'s' if len(missing) > 1 else ''} "
                          f"{', '.join(missing)} (is it the file `spadscan sweep` writes?)")
    return rows


__all__ = ["SweepResults", "read_results", "number", "value_key"]
