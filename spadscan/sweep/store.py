"""A sweep's results folder: what survives a crash, a killed worker and a re-run.

    DIR/sweep.json          the fingerprint of the base condition and methods, the grid, the entries (see plan.py)
    DIR/sweep.toml          a copy of the sweep file last run here (its relative mesh paths are relative to the
                            original's folder: sweep.json's sweep_file)
    DIR/points/<id>.json    one finished point (done or failed), written at once and atomically by the worker;
                            with each method's fingerprint (fingerprint.py): a stale point runs again
    DIR/results.csv         every grid entry that has a result, one row each, gathered from points/
    DIR/log.jsonl           what happened when: each point's start and stages, on which worker, and its end
    DIR/work/               points in progress (their capture and outputs; removed when they end unless kept)
    DIR/locks/<id>          held (flock) by the attempt that runs the point, while it runs
    DIR/.lock               held by the one `spadscan sweep` that runs on DIR

Machines that run points must share this folder (the same path on each).
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import io
import json
import os
import secrets
import shutil
import time
from pathlib import Path
from typing import Callable

import spadscan
from spadscan.protocol.atomic_files import write_atomic
from spadscan.protocol.errors import ConfigError

from .params import C_M_PER_S

SWEEP_JSON = "sweep.json"
SWEEP_TOML = "sweep.toml"
POINTS = "points"
RESULTS_CSV = "results.csv"
LOG = "log.jsonl"
WORK = "work"
LOCK = ".lock"
LOCKS = "locks"
RUNNING_MARK = ".running-"
"""In the name of a point's work folder while it runs: <id>.running-<host>-<pid>-<token>."""

PARAM_COLUMNS = ("sensor", "schedule", "views", "rings", "min_elevation_deg", "max_elevation_deg", "radius_m",
                 "bin_ps", "fov_deg", "power", "ambient", "cycles", "albedo", "rays_per_zone", "seed")
METRIC_COLUMNS = ("chamfer_mm", "accuracy_mm", "completeness_mm", "fscore_5mm", "normal_error_deg", "seconds")
PRESET_COLUMNS = ("steps", "stopped_by")
BASELINE_COLUMNS = ("threshold",)
PRESET_END_COLUMNS = ("converged", "warning_count", "warnings")
BASELINE_END_COLUMNS = ("threshold_edge", "warning_count", "warnings")
"""How each method's run ended, after every method's other columns: `converged` (True or False, a preset's),
`warning_count` (0 for a clean run) and `warnings` (its one-line warnings joined by WARNINGS_JOIN), empty where the
method gave no result or its record predates them; `threshold_edge` ('lowest', 'highest' or 'only': the calibrated threshold is at
the end of the thresholds tried, so one beyond them might have done better)."""
WARNINGS_JOIN = " | "


def write_json_atomic(path: Path, data: dict) -> None:
    """Replace `path` atomically (`write_atomic`: its temporary file is this writer's own, so two attempts at one
    point that end at once on two machines do not collide)."""
    write_atomic(path, json.dumps(data, indent=1, allow_nan=False) + "\n")


def column_name(method: str) -> str:
    """'space-carving' -> 'space_carving' (a CSV column prefix)."""
    return method.replace("-", "_")


class SweepDir:
    """The results folder of a sweep (see the module docstring)."""

    def __init__(self, path):
        self.path = Path(path)
        self.points = self.path / POINTS
        self.work = self.path / WORK
        self.locks = self.path / LOCKS
        self._lock_fd: int | None = None
        self._opened = False

    # --- the client's side: open, check, gather ---------------------------------------------------------------

    def open(self, plan, overwrite: bool = False) -> None:
        """Create or reopen the folder for `plan`: take the lock, refuse a folder of another base condition, or
        (unless `overwrite`) one holding results of grid entries that `plan` lacks, record the plan, clear the work
        folders of attempts that died (not those of attempts still running: an interrupted run's points go on
        running on a scheduler's workers). Call `close` when done."""
        if self.path.exists() and not self.path.is_dir():
            raise ConfigError(f"{self.path}: exists and is not a folder")
        self.path.mkdir(parents=True, exist_ok=True)
        new_lock = not (self.path / LOCK).exists()
        self._lock()
        try:
            try:
                self._check_fingerprint(plan, overwrite)
            except ConfigError:
                if new_lock:  # a refused folder is left as it was found
                    (self.path / LOCK).unlink(missing_ok=True)
                raise
            self.points.mkdir(exist_ok=True)
            self.work.mkdir(exist_ok=True)
            self.locks.mkdir(exist_ok=True)
            self._clear_dead_work()
            write_json_atomic(self.path / SWEEP_JSON, sweep_record(plan))
            write_atomic(self.path / SWEEP_TOML, plan.spec.text)
            self._opened = True
        except BaseException:
            self.close()
            raise

    def _clear_dead_work(self) -> None:
        """Remove work/<id>.running-... folders whose point no attempt holds: the attempt that made each is dead (an
        attempt still running, on a scheduler's worker, holds its point's lock and keeps its folder)."""
        for folder in self.work.glob(f"*{RUNNING_MARK}*"):
            with self.hold_point(folder.name.split(RUNNING_MARK)[0], wait=False) as free:
                if free:
                    shutil.rmtree(folder, ignore_errors=True)

    def check(self, plan, overwrite: bool = False) -> None:
        """What `open` refuses, checked without taking the lock or writing anything (`spadscan sweep --dry-run`): a
        file in the way, a folder of other files, a folder of another base condition or of other grid entries."""
        if self.path.exists() and not self.path.is_dir():
            raise ConfigError(f"{self.path}: exists and is not a folder")
        if self.path.is_dir():
            self._check_fingerprint(plan, overwrite)

    def close(self) -> None:
        """Clear the work folders of attempts that died during the run (a killed worker's), then let the folder go.
        A folder `open` refused is left as it was found."""
        if self._opened:
            self._opened = False
            with contextlib.suppress(OSError):  # a leftover folder is untidy, not wrong: the next open clears it
                self._clear_dead_work()
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the lock
            self._lock_fd = None

    def _lock(self) -> None:
        fd = os.open(self.path / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip()
            os.close(fd)
            who = f" (pid {holder})" if holder else ""
            raise ConfigError(f"{self.path}: another `spadscan sweep` is running on this folder{who}; wait for it "
                              f"or choose another --out") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._lock_fd = fd

    def _check_fingerprint(self, plan, overwrite: bool = False) -> None:
        path = self.path / SWEEP_JSON
        if not path.exists():
            if any(p.name != LOCK for p in self.path.iterdir()):
                raise ConfigError(f"{self.path}: holds other files and no {SWEEP_JSON}: not a sweep's folder (choose "
                                  f"a new or empty --out)")
            return
        try:
            old = json.loads(path.read_text())
            old_fingerprint, old_base = old["fingerprint"], old["base_record"]
        except (OSError, ValueError, KeyError, TypeError):
            raise ConfigError(f"{path}: unreadable; this folder cannot be checked against the sweep (choose "
                              f"another --out)") from None
        if old_fingerprint == plan.fingerprint:
            if not overwrite:
                self._check_entries(old, plan, path)
            return
        if not any(self.points.glob("*.json")):
            return  # no point stored (a run that never reached its cluster, say): nothing to keep apart
        changed = differences(old_base, plan.base_record)
        shown = ", ".join(changed[:4]) + (f" and {len(changed) - 4} more" if len(changed) > 4 else "")
        raise ConfigError(f"{self.path} holds points of another base condition ({shown or 'a different format'}); "
                          f"its results would not be comparable with this sweep's: choose another --out, or "
                          f"{self._restore_advice(old.get('sweep_file'))}")

    def _check_entries(self, old: dict, plan, path: Path) -> None:
        """Refuse a plan that lacks grid entries the folder holds results of: results.csv and sweep.json (so the
        figure) are the plan's entries alone, and would lose those rows. The same sweep, or a grown grid, passes."""
        entries = old.get("entries", [])
        if not isinstance(entries, list) or not all(isinstance(e, dict) and isinstance(e.get("point"), str)
                                                    for e in entries):
            raise ConfigError(f"{path}: unreadable (its entries); this folder cannot be checked against the sweep "
                              f"(choose another --out)")
        planned = {entry_key(e.scene, e.axis, e.value, e.point_id) for e in plan.entries}
        dropped = [e for e in entries if entry_key(e.get("scene"), e.get("axis"), e.get("value"), e["point"])
                   not in planned and self.read_point(e["point"]) is not None]
        if not dropped:
            return
        shown = ", ".join(_describe_entry(e) for e in dropped[:3]) + (
            f" and {len(dropped) - 3} more" if len(dropped) > 3 else "")
        raise ConfigError(f"{self.path} holds results of {len(dropped)} grid entr{'y' if len(dropped) == 1 else 'ies'} "
                          f"this sweep file lacks ({shown}), which results.csv and sweep-plot would lose: choose "
                          f"another --out, grow this file's grid to hold them (the file last run here is "
                          f"{self.path / SWEEP_TOML}), or add --overwrite (their points stay in {self.points})")

    def _restore_advice(self, sweep_file) -> str:
        """How to run this folder's own sweep again. The copy in DIR is not run where it is: a scene that is a
        relative mesh path is relative to the original file's folder, so the copy goes back there."""
        copy = self.path / SWEEP_TOML
        if not isinstance(sweep_file, str) or not sweep_file:
            return f"restore the sweep file it was run with (its text is in {copy}) and run that"
        return (f"run the sweep file it was run with, {sweep_file} (if it has changed since, copy {copy} over it "
                f"first: its scenes' relative paths are relative to that file's folder)")

    def write_results(self, plan, current=None) -> int:
        """Gather every grid entry of `plan` that has a result into results.csv (atomically); returns the rows.
        `current(point_id, result)`: whether a stored result is this run's to show (fingerprint.py; the runner's):
        a stale one, which runs again, is left out until it has, so that one figure never mixes the results of two
        versions, devices or defaults (its file stays in points/)."""
        methods = plan.spec.methods
        header = ["scene", "axis", "value", "point", "status", "reason", *PARAM_COLUMNS, "bin_mm"]
        presets = {p.name for p in plan.spec.presets}
        for m in methods:
            extra = PRESET_COLUMNS if m in presets else BASELINE_COLUMNS
            header += [f"{column_name(m)}_{c}" for c in ("status", *METRIC_COLUMNS, *extra)]
        for m in methods:  # after every earlier column: a script that reads them by position reads them as before
            header += [f"{column_name(m)}_{c}" for c in end_columns(m in presets)]
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(header)
        rows = 0
        cache: dict[str, dict | None] = {}
        for entry in plan.entries:
            if entry.point_id not in cache:
                cache[entry.point_id] = self.read_point(entry.point_id)
            result = cache[entry.point_id]
            if result is None or (current is not None and not current(entry.point_id, result)):
                continue
            writer.writerow(results_row(entry, result, methods, plan.spec))
            rows += 1
        write_atomic(self.path / RESULTS_CSV, buf.getvalue())
        return rows

    def endings(self, plan) -> tuple[dict[str, list[str]], dict[str, list[str]]]:
        """Of the points of `plan` that have a result: those where a method warned ({id: methods}, warned_methods)
        and those where a baseline's calibrated threshold is at an end of the thresholds tried (edge_methods)."""
        warned, edge = {}, {}
        for point_id in plan.points:
            result = self.read_point(point_id)
            if result is None:
                continue
            if methods := warned_methods(result):
                warned[point_id] = methods
            if methods := edge_methods(result):
                edge[point_id] = methods
        return warned, edge

    # --- both sides ---------------------------------------------------------------------------------------------

    def read_point(self, point_id: str) -> dict | None:
        """The stored result of a point, or None when there is none (or it cannot be read: it runs again)."""
        path = self.points / f"{point_id}.json"
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            return None
        return data if isinstance(data, dict) and data.get("id") == point_id else None

    def write_point(self, result: dict, expected=None) -> dict:
        """Store a point's result; returns what is stored. A `done` result already there stays: an attempt that
        failed (its worker died, it was cut short) says nothing against another attempt that finished. With
        `expected` (fingerprint.Expected), only a current one stays: a stale result is replaced by the new one."""
        if result.get("status") != "done":
            stored = self.read_point(result["id"])
            if stored is not None and stored.get("status") == "done" and (
                    expected is None or expected.state(stored) == "done"):
                return stored
        write_json_atomic(self.points / f"{result['id']}.json", result)
        return result

    @contextlib.contextmanager
    def hold_point(self, point_id: str, wait: bool = True, on_wait: Callable[[], None] | None = None):
        """Hold the point's lock (DIR/locks/<id>) for the block: yields True once held; with wait=False, yields
        False at once when another attempt holds it. `on_wait()` is called before waiting for one. The lock is an
        flock, so it goes with its holder's process however that ends (on NFS, the client's locks are the
        server's: a dead machine's go when its lease expires)."""
        self.locks.mkdir(exist_ok=True)
        # The file is never removed: one removed while another attempt waits on it would let a third lock a new one.
        fd = os.open(self.locks / point_id, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if not wait:
                    yield False
                    return
                if on_wait is not None:
                    on_wait()
                fcntl.flock(fd, fcntl.LOCK_EX)
            yield True
        finally:
            os.close(fd)  # releases the lock

    def append_log(self, event: dict) -> None:
        """One line of log.jsonl (only the client writes it: one writer, whole lines)."""
        line = json.dumps({"utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **event}) + "\n"
        with open(self.path / LOG, "a") as f:
            f.write(line)

    def new_work_dir(self, point_id: str, host: str) -> Path:
        path = self.work / f"{point_id}{RUNNING_MARK}{host}-{os.getpid()}-{secrets.token_hex(3)}"
        path.mkdir(parents=True)
        return path

    def finish_work_dir(self, path: Path, point_id: str, keep: bool) -> Path | None:
        """Remove a point's work folder, or with `keep` move it to work/<id> (replacing an older one)."""
        if not keep:
            shutil.rmtree(path, ignore_errors=True)
            return None
        final = self.work / point_id
        if final.exists():
            shutil.rmtree(final, ignore_errors=True)
        os.replace(path, final)
        return final


def sweep_record(plan) -> dict:
    """What sweep.json holds: the fingerprint and what it is made of, the grid and every entry."""
    spec = plan.spec
    return {
        "format": 1,
        "fingerprint": plan.fingerprint,
        "base_record": plan.base_record,
        "sweep_file": str(spec.path.resolve()),
        "mode": spec.mode,
        "scenes": [s.label for s in plan.scenes],
        "methods": list(spec.methods),
        "presets": [p.name for p in spec.presets],
        "grid": spec.grid,
        "base": spec.base,
        "entries": [{"scene": e.scene, "axis": e.axis, "value": e.value, "point": e.point_id}
                    for e in plan.entries],
        "points": len(plan.points),
        "spadscan": spadscan.__version__,
    }


def entry_key(scene, axis, value, point_id) -> str:
    """A grid entry as text that compares equal for the same entry, in a plan or read back from sweep.json."""
    return json.dumps([scene, axis, value, point_id])


def _describe_entry(entry: dict) -> str:
    """'builtin:sphere views=8' for a sweep.json entry."""
    axis, value = entry.get("axis"), entry.get("value")
    if value is None:  # the base alone, or a product entry: the point names it
        return f"{entry.get('scene')} {axis} (point {entry.get('point')})"
    shown = f"{value:g}" if isinstance(value, (int, float)) and not isinstance(value, bool) else value
    return f"{entry.get('scene')} {axis}={shown}"


def results_row(entry, result: dict, methods, spec) -> list:
    params = result.get("params", {})
    presets = {p.name for p in spec.presets}
    bin_mm = params["bin_ps"] * 1e-12 * C_M_PER_S / 2 * 1e3 if "bin_ps" in params else ""
    row = [entry.scene, entry.axis, "" if entry.value is None else _cell(entry.value), entry.point_id,
           result.get("status", ""), result.get("reason") or "", *(_cell(params.get(c)) for c in PARAM_COLUMNS),
           _cell(bin_mm)]
    for m in methods:
        r = result.get("methods", {}).get(m, {})
        extra = PRESET_COLUMNS if m in presets else BASELINE_COLUMNS
        row += [r.get("status", "not run"), *(_cell(r.get(c)) for c in (*METRIC_COLUMNS, *extra))]
    for m in methods:
        r = result.get("methods", {}).get(m, {})
        ended = ending_cells(r)
        row += [_cell(ended[c] if c in ended else r.get(c)) for c in end_columns(m in presets)]
    return row


def end_columns(preset: bool) -> tuple[str, ...]:
    """How a method's run ended: its columns, which follow every method's others (the columns of earlier versions
    keep their places)."""
    return PRESET_END_COLUMNS if preset else BASELINE_END_COLUMNS


def method_warnings(record: dict) -> list[str] | None:
    """A method's warnings in its point record (a list of one-line strings), or None where it has none to give: it
    failed, or its record predates them."""
    warnings = record.get("warnings")
    if record.get("status") != "done" or not isinstance(warnings, list):
        return None
    return [" ".join(str(w).split()) for w in warnings]


def ending_cells(record: dict) -> dict:
    """The cells of PRESET_END_COLUMNS and BASELINE_END_COLUMNS that are not the record's values as they are."""
    warnings = method_warnings(record)
    return {"warning_count": None if warnings is None else len(warnings),
            "warnings": None if warnings is None else WARNINGS_JOIN.join(warnings)}


def warning_count(record: dict) -> int:
    """How many reasons to doubt a method's result its point record gives: its warnings, or 1 for a preset that did
    not converge and says nothing of it (0 for a method that failed: it has no result to doubt)."""
    warnings = method_warnings(record) or []
    return len(warnings) or int(record.get("status") == "done" and record.get("converged") is False)


def warning_counts(result: dict) -> dict[str, int]:
    """{method: warning_count} of the methods of a point's result that warned."""
    return {m: n for m, r in (result.get("methods") or {}).items() if isinstance(r, dict) and (n := warning_count(r))}


def warned_methods(result: dict) -> list[str]:
    """The methods of a point's result that gave a result and warned: a warning, or a preset that did not converge."""
    return list(warning_counts(result))


def edge_methods(result: dict) -> list[str]:
    """The baselines of a point's result whose calibrated threshold is at an end of the thresholds tried."""
    return [m for m, r in (result.get("methods") or {}).items()
            if isinstance(r, dict) and r.get("status") == "done" and r.get("threshold_edge")]


def _cell(value):
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return value


def differences(old, new, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two JSON-like dicts, as 'key: old -> new'."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for key in sorted(set(old) | set(new), key=str):
            out += differences(old.get(key), new.get(key), f"{prefix}{key}.")
        return out
    if old != new:
        return [f"{prefix.rstrip('.')}: {json.dumps(old)} -> {json.dumps(new)}"]
    return []


__all__ = ["SweepDir", "write_json_atomic", "differences", "column_name", "sweep_record", "method_warnings",
           "warned_methods", "warning_count", "warning_counts", "edge_methods", "SWEEP_JSON", "POINTS", "RESULTS_CSV",
           "LOG", "WORK", "LOCKS", "WARNINGS_JOIN"]
