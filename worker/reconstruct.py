"""Reconstruct one capture: load it, build the preset's model, train, extract the mesh, write the report.

`reconstruct_capture` is what `spadscan reconstruct` and the worker's job processes call. It writes into `out`:
mesh.ply (per-vertex normals from the SDF gradient), report.json, report.html (the page to open first),
preview.png, error_vs_time.png, fit.png, and with ground truth normals.png (per-vertex normal error). `set_up_run`
is its first half (the resolved config, the loaded capture, the model, the plan), which the benchmarks share.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

import spadscan
from spadscan.protocol.capture_reader import check_capture_counts
from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.mesh_io import MM_EXTENT_THRESHOLD_M

from .ground_truth import load_ground_truth
from .metrics import mesh_metrics
from .outputs import capture_state_note, export_mesh
from .recon.config import ReconConfig, with_overrides
from .recon.errors import ReconstructionError
from .recon.model_api import ReconModel, RunPlan
from .recon.presets import make_model, preset_config
from .recon.scene_data import SceneData, load_scene
from .recon.trainer import train
from .report import pictures
from .report.report_html import write_report_html
from .report.report_json import json_safe, write_report
from .threads import check_threads, machine_cores

DEVICES = ("auto", "cpu", "cuda")
FIT_VIEWS = 4


def resolve_device(device: str) -> torch.device:
    """torch.device for 'auto' (CUDA when torch sees a GPU, else CPU), 'cpu' or 'cuda' (an error without a GPU)."""
    if device not in DEVICES:
        raise ReconstructionError(f"device {device!r} must be one of {', '.join(DEVICES)}")
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ReconstructionError("device 'cuda' asked for, but torch sees no CUDA device (use --device cpu or auto)")
    return torch.device(device)


def _check_run_args(budget_s, steps, seed) -> None:
    if budget_s is not None and not (isinstance(budget_s, (int, float)) and np.isfinite(budget_s) and budget_s > 0):
        raise ReconstructionError(f"time budget {budget_s} s must be a positive number of seconds")
    if steps is not None and not (isinstance(steps, (int, np.integer)) and steps >= 1):
        raise ReconstructionError(f"steps {steps} must be an integer >= 1")
    if not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise ReconstructionError(f"seed {seed} must be an integer >= 0")


def run_config(preset: str, overrides: dict | None = None) -> ReconConfig:
    """The resolved config of `preset` with dotted-key `overrides` (see config.with_overrides)."""
    config = preset_config(preset)
    return with_overrides(config, overrides) if overrides else config


LONG_CPU_STEPS = 20_000
"""A default step count this large is worth a warning on a CPU (the paper preset: seconds a step there)."""


@dataclass
class Run:
    """A reconstruction set up and ready to train."""

    config: ReconConfig
    """The resolved config (overrides included)."""
    scene: SceneData
    """The loaded capture."""
    model: ReconModel
    """The preset's model, built on the scene."""
    plan: RunPlan
    """Steps and time budget the model was laid out for, and the seed."""
    device: torch.device
    state_note: str | None
    """Why the capture may be doubtful (not complete), or None."""
    setup_s: float
    """Wall seconds that loading the capture and building the model took."""


def set_up_run(capture: Path, config: ReconConfig, device: torch.device, *, steps: int | None,
               budget_s: float | None, seed: int, log: Callable[[str], None], make: Callable | None = None) -> Run:
    """Load the capture and build the preset's model: what every run does before it trains. With neither `steps`
    nor `budget_s`, the preset's defaults bound the run. `make`: a model factory (scene, config, device, plan) ->
    model in place of the preset's (a live job's final run starts its model from the live fit)."""
    t0 = time.perf_counter()
    check_capture_counts(capture, log)  # histograms no sensor could produce: refused, or warned about
    dtype = torch.float64 if config.tensor_dtype() == "float64" else torch.float32
    scene = load_scene(Path(capture), device, dtype)
    state_note = capture_state_note(capture, scene.state, scene.n_views)
    if state_note:
        log(f"warning: {state_note}")
    if steps is None and budget_s is None:
        steps, budget_s = config.default_steps, config.default_budget_s
        if budget_s is None and device.type == "cpu" and (steps or 0) >= LONG_CPU_STEPS:
            log(f"warning: preset {config.preset!r} runs {steps:,} steps by default: days on a CPU (--budget-s or "
                f"--steps to bound it)")
    plan = RunPlan(steps=steps, budget_s=budget_s, seed=int(seed))
    model = (make or make_model)(scene, config, device, plan)
    return Run(config, scene, model, plan, device, state_note, time.perf_counter() - t0)


def reconstruct_capture(capture: Path, out: Path, *, preset: str = "fast", budget_s: float | None = None,
                        steps: int | None = None, gt: Path | None = None, device: str = "auto", seed: int = 0,
                        progress: bool = True, overrides: dict | None = None, threads: int | None = None,
                        log: Callable[[str], None] | None = None, make: Callable | None = None) -> dict:
    """Reconstruct `capture` into folder `out` with preset `preset`; returns the report dict (also report.json).

    The run stops after `steps` steps or `budget_s` seconds of training and checkpoint evaluation, whichever comes
    first (neither: the preset's defaults). `gt`: a ground-truth mesh file; adds Chamfer, accuracy, completeness,
    F-score and normal errors, and Chamfer at every trace checkpoint. `overrides`: dotted config keys to change (see
    config.with_overrides). `threads`: torch's CPU threads (default: as torch starts, OMP_NUM_THREADS or the
    cores). `log`: receives a line per stage after training (mesh, metrics, pictures) and warnings. `make`: a model
    factory in place of the preset's (see `set_up_run`)."""
    log = log or (lambda line: None)
    wall0 = time.perf_counter()
    _check_run_args(budget_s, steps, seed)
    if threads is not None:
        torch.set_num_threads(check_threads(threads))
        if threads > machine_cores():
            log(f"warning: {threads} CPU threads on {machine_cores()} cores: OpenMP threads that lose their core "
                f"stall each other, each step many times slower (--threads {machine_cores()} or fewer)")
    config = run_config(preset, overrides)
    dev = resolve_device(device)
    truth = load_ground_truth(gt) if gt is not None else None  # a bad one fails before hours of training
    if truth is not None and truth.units_read == "mm":
        log(f"ground truth {gt}: read as millimetres (over {MM_EXTENT_THRESHOLD_M:g} m across as metres)")
    run = set_up_run(capture, config, dev, steps=steps, budget_s=budget_s, seed=seed, log=log, make=make)
    model, scene, plan = run.model, run.scene, run.plan
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)  # only once the capture has loaded: a bad one leaves no empty folder

    evaluate = None
    if truth is not None:
        evaluate = lambda: _checkpoint_metrics(model, truth, config)  # noqa: E731
    result = train(model, plan, checkpoints=config.trace_checkpoints, evaluate=evaluate, progress=progress,
                   desc=f"reconstruct ({preset})", score_note=f"checkpoint {checkpoint_scoring(config, short=True)}",
                   early_stop=config.early_stop)

    log(f"extracting the mesh ({config.mesh_resolution} cells a side)")
    mesh = model.extract_mesh(config.mesh_resolution)
    export_mesh(mesh, out / "mesh.ply", vertex_normal=True)
    report = _report(capture, preset, dev, config, scene, model, result, plan, scored=truth is not None)
    report["capture_state"] = scene.state
    if run.state_note:
        report["capture_note"] = run.state_note
    if truth is not None:
        log(f"metrics against the ground truth ({config.metrics_points:,} points per mesh)")
        if truth.note():
            log(f"scoring {truth.note()}")
        report.update(truth.report_fields())
        scored = truth.scored(mesh)  # cut once for the metrics and the normals picture
        report.update(mesh_metrics(scored, truth.mesh, n_points=config.metrics_points, seed=int(seed)).to_dict())
        report["chamfer_scoring"] = final_scoring(config)
        vertex_err = pictures.vertex_normal_error_deg(scored, truth.mesh)
        report["vertex_normal_error_deg"] = {"mean": float(vertex_err.mean()),
                                             "median": float(np.median(vertex_err))}
        pictures.normals_png(scored, vertex_err, out / "normals.png")
        report["ground_truth"] = str(gt)
    log("pictures and report")
    _pictures(out, mesh, None if truth is None else truth.mesh, model, scene, result, config)
    report["files"] = sorted(p.name for p in out.iterdir() if p.is_file() and not p.name.startswith("."))
    report["files"] = sorted(set(report["files"]) | {"report.json", "report.html"})
    report["wall_seconds"] = time.perf_counter() - wall0
    write_report(out, report)
    report = json_safe(report)
    write_report_html(report, out)
    return report


def checkpoint_scoring(config: ReconConfig, short: bool = False) -> str:
    """How checkpoints are scored, for every place their Chamfer is shown: coarser than the final mesh. short: no
    commas (for the progress bar's fields)."""
    points = f"{config.trace_points / 1000:g}k" if short and config.trace_points >= 1000 else f"{config.trace_points:,}"
    return f"{config.trace_mesh_resolution}-cell mesh{';' if short else ','} {points} points"


def final_scoring(config: ReconConfig) -> str:
    """How the final mesh is scored (the summary's Chamfer)."""
    return f"final {config.mesh_resolution}-cell mesh, {config.metrics_points:,} points"


def _checkpoint_metrics(model, truth, config: ReconConfig) -> dict:
    """Chamfer of the current surface against a GroundTruth at a trace checkpoint (fewer points, coarser mesh than
    the final one)."""
    try:
        pred = model.extract_mesh(config.trace_mesh_resolution)
        return {"chamfer_mm": truth.metrics(pred, n_points=config.trace_points).chamfer_mm}
    except SpadscanError as exc:  # no surface yet, or a degenerate one: the trace says so, the run goes on
        return {"chamfer_mm": None, "note": str(exc)}


def _trace_note(eval_seconds: float, config, scored: bool) -> str:
    """What the trace's figures mean; the clause on checkpoint Chamfer only when there is a ground truth to score."""
    parts = [f"'seconds' is training time only: checkpoint evaluation ({eval_seconds:.1f} s in all) is excluded (a "
             f"time budget counts it)"]
    if scored:
        parts.append(f"checkpoint Chamfer uses {config.trace_points} points per mesh on a "
                     f"{config.trace_mesh_resolution}-cell marching-cubes grid, the final metrics "
                     f"{config.metrics_points} points on {config.mesh_resolution} cells")
    parts.append("'loss' is the mean since the previous checkpoint")
    return "; ".join(parts)


def _report(capture, preset, dev, config, scene, model, result, plan, scored: bool) -> dict:
    last = result.last
    tail = result.losses[-max(1, len(result.losses) // 10):] if result.losses else []
    return {
        "capture": str(Path(capture).resolve()),
        "preset": preset,
        "device": str(dev),
        "device_name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
        "torch_threads": torch.get_num_threads(),
        "seed": plan.seed,
        "steps": result.steps,
        "seconds": result.seconds,
        "seconds_per_step": result.seconds / result.steps if result.steps else None,
        "stopped_by": result.stopped_by,
        "eval_seconds": result.eval_seconds,
        "plan": {"steps": plan.steps, "budget_s": plan.budget_s},
        "terms": model.terms.to_dict(),
        "final_loss": float(last["loss"]) if last else None,
        "final_loss_mean_last_10pct": float(np.mean(tail)) if tail else None,
        "loss_parts": last,
        "trace": result.trace,
        "trace_note": _trace_note(result.eval_seconds, config, scored),
        "model": model.summary(),
        "scene": {
            "views": scene.n_views, "zones": scene.sensor.n_zones, "bins": scene.sensor.n_bins,
            "sensor": scene.sensor.name, "real": scene.real, "center_m": scene.center.tolist(),
            "radius_m": scene.radius, "background": scene.background_source, "pulse": scene.pulse_source,
            "table": None if scene.table is None else {"normal": scene.table.normal.tolist(),
                                                       "offset_m": scene.table.offset, "fitted": scene.table.fitted},
        },
        "config": config.to_dict(),
        "versions": {"spadscan": spadscan.__version__, "torch": torch.__version__},
    }


def _pictures(out: Path, mesh, gt_mesh, model, scene, result, config: ReconConfig) -> None:
    pictures.preview_png(mesh, out / "preview.png", gt=gt_mesh)
    scoring = "" if gt_mesh is None else f" (checkpoint Chamfer: {checkpoint_scoring(config)})"
    pictures.error_vs_time_png(result.trace, out / "error_vs_time.png",
                               title=f"{config.preset}: error against run time{scoring}")
    n = scene.n_views
    views = sorted({int(round(i)) for i in np.linspace(0, n - 1, min(FIT_VIEWS, n))})
    rendered = model.render_histograms(views)
    measured = scene.counts[views].double().cpu().numpy()
    pictures.fit_png(measured, rendered, views, out / "fit.png")
