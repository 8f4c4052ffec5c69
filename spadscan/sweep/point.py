"""One point of a sweep: simulate the capture, run each preset and each calibrated baseline, score, record.

`run_point` is what a Dask worker runs (runner.py wraps it) and what a plain loop in one process runs. It uses one
CPU thread for torch (the cluster runs one point per worker process, one process per core), writes its result to
DIR/points/<id>.json before it returns, and never raises for a failed stage: each method's failure is recorded with
its one-line reason, the others still run, and the point is `failed` with their reasons (the methods that failed for
one cause named together: "every method: ..." when all did). Reasons and warnings name the point's capture, not
its temporary work folder, which is gone when the point ends. A point whose result is
already there as `done` (its worker died after writing it, and Dask ran it again) is not run twice, and an attempt
waits while another holds the point (an interrupted run's attempt, which goes on running on a scheduler's worker)
and then takes that one's result. A point stored earlier runs only its methods that are not stored done and current
(fingerprint.py): a failed point's methods that were done are kept, not run again (a `paper` preset takes hours);
a stale method (another spadscan version, device, or preset or threshold defaults) runs again. The stored file is
replaced only once the new result is written.
"""

from __future__ import annotations

import os
import socket
import time
import traceback
from pathlib import Path
from typing import Callable

import spadscan
from spadscan.protocol.capture_format import one_line
from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.simulator import simulate_capture
from spadscan.worker.baselines.common import threshold_edge
from spadscan.worker.baselines.run import run_baseline
from spadscan.worker.reconstruct import reconstruct_capture
from spadscan.worker.report.report_json import json_safe

from .fingerprint import Expected
from .params import point_poses, point_sensor, point_settings
from .plan import PointTask
from .scenes import scene_mesh
from .store import SweepDir, warning_counts

Emit = Callable[..., None]
"""emit(event, **fields): 'wait' (another attempt holds the point), 'start', 'stage' (stage=NAME), 'done',
'failed', 'skip'."""

PRESET_KEYS = ("chamfer_mm", "accuracy_mm", "completeness_mm", "fscore_5mm", "normal_error_deg", "steps",
               "stopped_by", "final_loss", "device", "converged", "warnings")
"""What a point keeps of a preset's report.json: `converged` and `warnings` (one-line reasons to doubt the result,
docs/end_of_run.md) say whether a result that has numbers ended well."""
BASELINE_KEYS = ("chamfer_mm", "accuracy_mm", "completeness_mm", "fscore_5mm", "normal_error_deg", "threshold",
                 "floor_z_m", "warnings")
CAPTURE_NAME = "the point's capture"
WORK_NAME = "the point's work folder"
"""What a reason or a warning says in place of the point's temporary work folder (removed, or moved by --keep, when
the point ends): its path would lead nowhere."""


def run_point(task: PointTask, out: str, *, device: str = "cpu", keep: bool = False,
              emit: Emit | None = None, worker: str | None = None) -> dict:
    """Run `task` and store its result in the sweep folder `out`; returns the result (as stored)."""
    emit = emit or (lambda event, **fields: None)
    store = SweepDir(out)
    expected = Expected(task, device)
    earlier = store.read_point(task.id)
    if expected.state(earlier) == "done":
        emit("skip")
        return earlier
    with store.hold_point(task.id, on_wait=lambda: emit("wait")):
        latest = store.read_point(task.id)
        # A result written since the first look is another attempt's, which held the point meanwhile: the point ran
        # (unless that attempt's code or device was another: its result is stale, and the point runs again).
        if expected.state(latest) == "done" or (latest is not None and latest != earlier and all(
                expected.current(latest, name) for name in expected.fingerprints)):
            emit("skip")
            return latest
        return _run(task, store, device, keep, emit, worker, expected, latest)


def _run(task: PointTask, store: SweepDir, device: str, keep: bool, emit: Emit, worker: str | None,
         expected: Expected, stored: dict | None = None) -> dict:
    """Run `task` (its lock held) and store its result; the methods that `stored` (the point's stored result) holds
    done and current are kept as they are, not run again."""
    host = socket.gethostname()
    kept_methods = expected.reusable(stored)
    emit("start", **({"kept": list(kept_methods)} if kept_methods else {}))
    start = time.perf_counter()
    methods: dict[str, dict] = {}
    simulation: dict = {}
    names = [p.name for p in task.presets] + list(task.baselines.methods)
    if all(name in kept_methods for name in names):  # nothing left to run: the capture is not simulated again
        simulation = dict((stored or {}).get("simulation") or {"status": "done"})
        methods = {name: kept_methods[name] for name in names}
        work = kept = None
    else:
        work = store.new_work_dir(task.id, host)
    try:
        if work is not None:
            emit("stage", stage="simulate")
            simulation = _attempt(lambda: _simulate(task, work))
            if simulation.get("status") == "done":
                capture = work / "capture"
                for preset in task.presets:
                    if preset.name in kept_methods:
                        methods[preset.name] = kept_methods[preset.name]
                        continue
                    emit("stage", stage=preset.name)
                    methods[preset.name] = _attempt(lambda: _reconstruct(task, preset, capture, work, device))
                for method in task.baselines.methods:
                    if method in kept_methods:
                        methods[method] = kept_methods[method]
                        continue
                    emit("stage", stage=method)
                    methods[method] = _attempt(lambda: _baseline(task, method, capture, work))
    finally:
        if work is not None:
            kept = store.finish_work_dir(work, task.id, keep)
    if work is not None:
        simulation = without_work_path(simulation, work)
        methods = {name: without_work_path(r, work) for name, r in methods.items()}
    reason = point_reason(simulation, methods)
    result = {
        "id": task.id,
        "status": "failed" if reason else "done",
        "reason": reason,
        "scene": task.scene.label,
        "params": task.params,
        "methods": methods,
        "simulation": simulation,
        "seconds": round(time.perf_counter() - start, 3),
        "worker": {"name": worker, "host": host, "pid": os.getpid()},
        "device": device,
        "work": None if kept is None else str(kept),
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "spadscan": spadscan.__version__,
        "record": task.record,
        "fingerprints": expected.fingerprints,
        "code": expected.code,
    }
    result = store.write_point(json_safe(result), expected)
    warned = warning_counts(result)  # log.jsonl's end of the point: which methods warned, how often
    emit(result["status"], reason=result["reason"], seconds=result["seconds"],
         **({"warnings": warned} if warned else {}))
    return result


def without_work_path(record: dict, work: Path) -> dict:
    """A stage's record with the point's temporary work folder named for what it is (CAPTURE_NAME, WORK_NAME) in its
    reason and warnings, whichever way the path was written (as given, or resolved)."""
    paths = sorted({str(work), str(work.resolve())}, key=len, reverse=True)

    def clean(text):
        if not isinstance(text, str):
            return text
        for path in paths:
            text = text.replace(f"{path}/capture", CAPTURE_NAME).replace(path, WORK_NAME)
        return text

    out = dict(record)
    if "reason" in out:
        out["reason"] = clean(out["reason"])
    if isinstance(out.get("warnings"), list):
        out["warnings"] = [clean(w) for w in out["warnings"]]
    return out


def point_reason(simulation: dict, methods: dict) -> str | None:
    """Why a point failed, in one line, or None when nothing failed: the simulation's reason, else each distinct
    reason once with the methods that failed for it ("every method: ..." when all did)."""
    if simulation.get("status") == "failed":
        return f"simulate: {simulation['reason']}"
    by_reason: dict[str, list[str]] = {}
    for name, r in methods.items():
        if r.get("status") == "failed":
            by_reason.setdefault(r.get("reason") or "failed", []).append(name)
    if not by_reason:
        return None
    if len(by_reason) == 1 and len(methods) > 1 and len(next(iter(by_reason.values()))) == len(methods):
        return f"every method: {next(iter(by_reason))}"
    return "; ".join(f"{', '.join(names)}: {reason}" for reason, names in by_reason.items())


def _attempt(run: Callable[[], dict]) -> dict:
    """run() with its failure turned into {'status': 'failed', 'reason': one line} (and the traceback kept for
    anything that is not one of spadscan's own errors)."""
    start = time.perf_counter()
    try:
        result = run()
    except SpadscanError as exc:
        return {"status": "failed", "reason": one_line(exc), "seconds": round(time.perf_counter() - start, 3)}
    except Exception as exc:  # noqa: BLE001 - a point's failure, whatever it is, must not stop the sweep
        return {"status": "failed", "reason": f"{type(exc).__name__}: {one_line(exc)}",
                "seconds": round(time.perf_counter() - start, 3), "traceback": traceback.format_exc()}
    return {"status": "done", **result, "seconds": round(time.perf_counter() - start, 3)}


def _simulate(task: PointTask, work: Path) -> dict:
    mesh, scene_record = scene_mesh(task.scene)
    poses, schedule = point_poses(task.params)
    sensor = point_sensor(task.params)
    settings = point_settings(task.params, task.base_bin_ps)
    notes: list[str] = []
    # Refused as `spadscan simulate` refuses it: a point whose sensor stood inside the object was simulated,
    # reconstructed, and plotted as an ordinary result 60 mm off, its note kept where nothing read it.
    simulate_capture(mesh, sensor, poses, work / "capture", settings=settings, seed=task.params["seed"],
                     scene=scene_record, schedule=schedule, progress=False, log=notes.append, refuse_misplaced=True)
    return {"views": int(len(poses)), "bins": int(sensor.n_bins), "bin_width_mm": sensor.bin_width_m * 1e3,
            "ambient_per_bin": settings.ambient, **({"note": " ".join(notes)} if notes else {})}


def _reconstruct(task: PointTask, preset, capture: Path, work: Path, device: str) -> dict:
    overrides = {**preset.overrides, "metrics_points": task.metrics_points}
    report = reconstruct_capture(capture, work / preset.name, preset=preset.name, budget_s=preset.budget_s,
                                 steps=preset.steps, gt=task.scene.source, device=device,
                                 seed=task.params["seed"], progress=False, overrides=overrides, threads=1)
    out = {k: report.get(k) for k in PRESET_KEYS}
    out["training_seconds"] = report.get("seconds")
    return out


def _baseline(task: PointTask, method: str, capture: Path, work: Path) -> dict:
    b = task.baselines
    report = run_baseline(capture, work / method, method, gt=task.scene.source, calibrate_=True,
                          resolution=b.resolution, thresholds=b.thresholds,
                          calibration_points=task.calibration_points, metrics_points=task.metrics_points)
    out = {k: report.get(k) for k in BASELINE_KEYS}
    out["calibration"] = [{"threshold": row["threshold"], "chamfer_mm": row["chamfer_mm"]}
                          for row in (report.get("calibration") or {}).get("table", [])]
    out["threshold_edge"] = threshold_edge(out["threshold"], [row["threshold"] for row in out["calibration"]])
    return out


__all__ = ["run_point", "point_reason", "without_work_path", "threshold_edge", "PRESET_KEYS",
           "BASELINE_KEYS"]
