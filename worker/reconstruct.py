"""Reconstruct one capture: load it, build the preset's model, train, extract the mesh, write the report.

`reconstruct_capture` is what `spadscan reconstruct` and the worker's job processes call. It writes into `out`:
mesh.ply (per-vertex normals from the SDF gradient), report.json, report.html (the page to open first),
preview.png, error_vs_time.png, fit.png, and with ground truth normals.png (per-vertex normal error). `set_up_run`
is its first half (the resolved config, the loaded capture, the model, the plan), which the benchmarks share.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np
import torch

import spadscan
from spadscan.protocol.capture_reader import CaptureReader, check_capture_counts
from spadscan.protocol.errors import CaptureError, SpadscanError
from spadscan.protocol.mesh_io import MM_EXTENT_THRESHOLD_M
from spadscan.protocol.pileup import coates_correct

from . import end_of_run
from .ambient_light import Ambient, ambient_warning, capture_ambient
from .budget import (FIXED_S, MIN_MESH_RESOLUTION, MIN_METRIC_POINTS, NORMALS_PICTURE_S, PROBE_POINTS,
                     PROBE_RESOLUTIONS, SAFETY, EndCosts, RunClock, coverage_picture_within, fit_views_within,
                     mesh_resolution_within, metric_points_within, probe_seconds, training_budget)
from .carving.bounds import floor_cut_note, mesh_share_below, returns_below_floor
from .carving.returns import DEFAULT_THRESHOLD, first_returns as detected_returns
from .carving.view_subset import spread_views
from .carving.views import summed_by_cycles
from .cpu_wait import ThreadWaits, machine_jobs, read_threads
from .coverage import FEW_VIEWS, Coverage, counted_views, few_share, summarize, surface_views, vertex_views
from .end_of_run import FitNoise, RunFacts, fit_noise
from .floor_gap import floor_gap, gap_warning
from .ground_truth import load_ground_truth
from .jobs import run_limits_problem
from .lost_returns import LostReturns, lost_returns
from .metrics import UNBUDGETED_S, mesh_metrics
from .outputs import capture_state_note, export_mesh, files_written_after, folder_files, replacing_result
from .pieces import Pieces, mesh_pieces
from .recon.config import ReconConfig, with_overrides
from .recon.errors import ReconstructionError
from .recon.fast.problem import carve_weak_threshold, default_thresholds
from .recon.model_api import ReconModel, RunPlan
from .recon.presets import make_model, preset_config
from .recon.scene_data import SceneData, load_scene
from .recon.trainer import train
from .report import pictures
from .report.folder_view import ensure_view3d
from .report.report_html import write_report_html
from .report.report_json import json_safe, write_report
from .signal_check import Signal, capture_signal, signal_warning
from .threads import ThreadGovernor, check_threads, machine_cores, threads_fixed
from .time_axis import NEAR_RANGE_M, check_time_axis, scene_views
from .top_reach import TopReach, top_reach, top_warning
from .view_spread import (above_only_warning, far_views_warning, low_only_warning, one_ring_warning,
                          small_object_warning, view_elevations_deg)

DEVICES = ("auto", "cpu", "cuda")
FIT_VIEWS = 4
"""Views the fit picture shows."""
NOISE_VIEWS = 32
"""Views the fit is compared with the photon noise on (end_of_run.fit_noise)."""
NOISE_RENDERS = 4
"""Renders of each of them averaged for that comparison (one for a model whose render is deterministic)."""
NEAR_PEAK_OVER = 5.0
"""How far (x their median) the photon rates' peak near the sensor stands above the rest when a surface touches
the sensor (`_why_no_return`): such a return piles up nearly every cycle, ambient light alone stays within its noise."""
COVERAGE_PROBE_VIEWS = 8
"""Views the probe of the coverage count counts every sample point of the probe's mesh on, spread among those the
report's count reads (`_probe_coverage`): an eighth or less of that count's time."""


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
    problem = run_limits_problem(budget_s, steps, seed)
    if problem:
        raise ReconstructionError(problem)


def _spent_at_set_up(elapsed_s: float, budget_s: float, preset: str, device: str) -> str:
    """The line said as training starts when the set-up has used the whole time budget: the run still makes the one
    step every run makes and its mesh, however long they take, and without this line it says so only at its end (the
    `paper` preset on a CPU: 45 s of set-up and a step of minutes against a 40 s budget)."""
    faster = end_of_run.faster_ways(preset, device, torch.cuda.is_available())
    return (f"warning: the set-up took {elapsed_s:.1f} s of the {budget_s:g} s time budget: training makes one step "
            f"(the {preset} preset's may take minutes on the {device}) and the run will end late; give it "
            f"{end_of_run.either(['a larger time budget', *faster])}")


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
    counts_note: str | None = None
    """Histograms no sensor could have produced (left out) or with clipped bins, in one line, or None: a warning of
    the run's too (a worker job has no terminal to print it on)."""


def set_up_run(capture: Path, config: ReconConfig, device: torch.device, *, steps: int | None,
               budget_s: float | None, seed: int, log: Callable[[str], None], defaulted: bool = False,
               make: Callable | None = None) -> Run:
    """Load the capture and build the preset's model: what every run does before it trains. With neither `steps`
    nor `budget_s`, the preset's defaults bound the run (`defaulted`: the caller already put them in); a default
    of days on a CPU is warned about once the capture has loaded (a bad capture is one error line, nothing more).
    `make`: a model factory (scene, config, device, plan) -> model in place of the preset's (a live job's final run
    starts its model from the live fit)."""
    t0 = time.perf_counter()
    counts_note = check_capture_counts(capture, log)  # histograms no sensor could produce: refused, or warned about
    dtype = torch.float64 if config.tensor_dtype() == "float64" else torch.float32
    scene = load_scene(Path(capture), device, dtype)
    check_signal_model(capture, scene.sensor)
    check_returns(capture, scene)
    state_note = capture_state_note(capture, scene.state, scene.n_views, CaptureReader(capture).manifest.get(
        "planned_poses"))
    if state_note:
        log(f"warning: {state_note}")
    if steps is None and budget_s is None:
        steps, budget_s, defaulted = config.default_steps, config.default_budget_s, True
    if defaulted:
        _warn_long_default(config, device, steps, budget_s, log)
    plan = RunPlan(steps=steps, budget_s=budget_s, seed=int(seed))
    model = (make or make_model)(scene, config, device, plan)
    return Run(config, scene, model, plan, device, state_note, time.perf_counter() - t0, counts_note)


def check_signal_model(capture, sensor) -> None:
    """Refuse (one CaptureError line) a capture whose sensor model predicts no signal in the fit's precision: its
    signal_scale 0, or it and every zone's gain so small that their product is no float32 number above 0. Every
    render would be background, and the mesh would be the carved hull while the run looked like a fit."""
    gain = max(z.gain for z in sensor.zones)
    if not np.float32(sensor.signal_scale * gain) >= np.finfo(np.float32).tiny:
        raise CaptureError(f"{capture}: the capture's sensor model predicts no signal (signal_scale "
                           f"{sensor.signal_scale:g}, the largest zone gain {gain:g}): nothing could be fitted; check "
                           f"the sensor record in its scan.json")


def check_returns(capture, scene) -> None:
    """Refuse (one CaptureError line) a capture in which no histogram holds a return above the noise, by the
    baselines' own test: a fit would shape a surface out of background alone and exit as if it had worked; then one
    whose strong returns lie where no surface of the scene can be (`check_time_axis`)."""
    counts = scene.counts.detach().cpu().numpy().astype(np.float64)
    if not detected_returns(counts, scene.sensor, DEFAULT_THRESHOLD).detected.any():
        raise CaptureError(f"{capture}: no histogram holds a return above the noise ({DEFAULT_THRESHOLD:g} standard "
                           f"deviations of its matched-filtered background): nothing to reconstruct "
                           f"({_why_no_return(counts, scene.cycles.detach().cpu().numpy(), scene.sensor)})")
    check_time_axis(capture, *scene_views(scene))


def _why_no_return(counts: np.ndarray, cycles: np.ndarray, sensor) -> str:
    """The likely cause of histograms (V, Z, B) of `cycles` (V,) laser cycles without a return: photons piled at the
    start of the range (a surface touching the sensor: its return ends in the first bins, where no peak can stand
    out), else the general causes. The photon rates are read through pile-up (`coates_correct`) before their peak is
    looked for, and it must stand NEAR_PEAK_OVER x over their median: a first-photon sensor's counts of ambient light
    alone fall bin by bin (fewer cycles are still live), and their highest bin, the first, was read as a surface
    touching the sensor."""
    rates = coates_correct(counts, cycles[:, None]) if sensor.pileup else counts
    total = rates.sum(axis=(0, 1))
    if sensor.ignore_bins:
        total[list(sensor.ignore_bins)] = 0.0
    peak = int(np.argmax(total))
    at = float(sensor.range_of_bin(peak + 0.5))
    if total[peak] > NEAR_PEAK_OVER * np.median(total) and total[peak] > 0 and at < NEAR_RANGE_M:
        return (f"the photons pile up {max(at, 0.0) * 1e3:.0f} mm from the sensor, at the start of its range: a "
                f"surface touching the sensor (move it back), or the sensor record's zero_bin wrong")
    return "the object out of range or out of every view, or the sensor's settings wrong"


def reconstruct_capture(capture: Path, out: Path, *, preset: str = "fast", budget_s: float | None = None,
                        steps: int | None = None, gt: Path | None = None, device: str = "auto", seed: int = 0,
                        progress: bool | str = True, overrides: dict | None = None, threads: int | None = None,
                        log: Callable[[str], None] | None = None, started: float | None = None,
                        clock: Callable[[], float] = time.perf_counter,
                        cpu_clock: Callable[[], float] = time.process_time, make: Callable | None = None,
                        after_training: Callable | None = None, stop: Callable[[], bool] | None = None,
                        thread_reader: Callable[[], dict | None] | None = read_threads,
                        polish: bool = False) -> dict:
    """Reconstruct `capture` into folder `out` with preset `preset`; returns the report dict (also report.json).

    `budget_s` bounds the whole run, from `started` (a `clock()` reading; default: now) to the report: set-up,
    training, mesh, metrics and pictures share it (budget.py: the mesh is coarser and the metrics use fewer points
    when time is short, and the report says so). `steps` bounds the training steps. Neither: the preset's defaults.
    `gt`: a ground-truth mesh file; adds Chamfer, accuracy, completeness, F-score and normal errors, and Chamfer at
    every trace checkpoint. `overrides`: dotted config keys to change (see config.with_overrides). `threads`:
    torch's CPU threads, kept for the whole run; without it (and without a user's OMP_NUM_THREADS) a CPU run
    chooses between torch's threads and one as it goes (threads.ThreadGovernor). `log`: receives a line per stage
    after training (mesh, metrics, pictures) and warnings. `progress`: training's bar on stderr (True), plain lines
    (trainer.PROGRESS_LINES) or nothing (False), as `trainer.train` takes it. The report says whether the run
    converged and why its result may be doubtful (`converged`, `warnings`: end_of_run.py). `clock` (wall seconds)
    and `cpu_clock` (this process's CPU seconds) time the run, and `thread_reader` gives its threads' seconds on a
    CPU and waiting for one (`cpu_wait.read_threads`; None: not measured), what a CPU run lost to other processes;
    tests inject their own.
    `stop()` true ends training at its next step, the mesh and report made as after a budget (the user's first
    Ctrl-C: `trainer.train`). `polish`: the run is a live job's final polish, its `steps` the live job's own choice
    (`end_of_run.RunFacts.polish`). A previous result in `out` (--overwrite) stays whole until this run has
    finished, and comes back if it does not (`outputs.replacing_result`)."""
    with replacing_result(out, log):
        return _reconstruct_into(capture, out, preset=preset, budget_s=budget_s, steps=steps, gt=gt, device=device,
                                 seed=seed, progress=progress, overrides=overrides, threads=threads, log=log,
                                 started=started, clock=clock, cpu_clock=cpu_clock, make=make,
                                 after_training=after_training, stop=stop, thread_reader=thread_reader,
                                 polish=polish)


def _reconstruct_into(capture: Path, out: Path, *, preset: str, budget_s: float | None, steps: int | None,
                      gt: Path | None, device: str, seed: int, progress: bool | str, overrides: dict | None,
                      threads: int | None, log: Callable[[str], None] | None, started: float | None,
                      clock: Callable[[], float], cpu_clock: Callable[[], float], make: Callable | None,
                      after_training: Callable | None, stop: Callable[[], bool] | None,
                      thread_reader: Callable[[], dict | None] | None, polish: bool = False) -> dict:
    """`reconstruct_capture`'s run, writing into `out`."""
    log = log or (lambda line: None)
    run_clock = RunClock(None, clock() if started is None else started, clock)
    before = folder_files(out)  # the user's own files there are no part of the result
    _check_run_args(budget_s, steps, seed)
    # other workers' job processes on this host, as the worker that started this run counted them: said in the busy
    # warning, whose cores they may have held
    siblings, bad_siblings = machine_jobs(os.environ)
    if bad_siblings:
        log(f"warning: {bad_siblings}")
    threads_note = None
    if threads is not None:
        torch.set_num_threads(check_threads(threads))
        threads_note = threads_warning(threads, machine_cores())
        if threads_note:
            log(f"warning: {threads_note}")  # at once, before training slows down; the report keeps it too
    config = run_config(preset, overrides)
    dev = resolve_device(device)
    truth = load_ground_truth(gt) if gt is not None else None  # a bad one fails before hours of training
    if truth is not None and truth.units_read == "mm":
        log(f"ground truth {gt}: read as millimetres (over {MM_EXTENT_THRESHOLD_M:g} m across as metres)")
    defaulted = steps is None and budget_s is None
    if defaulted:
        steps, budget_s = config.default_steps, config.default_budget_s
    run_clock.budget_s = budget_s
    costs = EndCosts(fixed_s=FIXED_S + (NORMALS_PICTURE_S if truth is not None else 0.0))
    checkpoint_cost = (config.trace_mesh_resolution, config.trace_points) if truth is not None else None
    end_s = costs.end_s(config.mesh_resolution, config.metrics_points if truth else None, checkpoint_cost)
    run = set_up_run(capture, config, dev, steps=steps, budget_s=training_budget(run_clock, end_s), seed=seed,
                     log=log, defaulted=defaulted, make=make)
    model, scene = run.model, run.scene
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)  # only once the capture has loaded: a bad one leaves no empty folder
    # What the capture (and the ground truth) alone decide, before training: both read every view (0.5 s at 2000
    # views, 4 s at 10,000), so a time budget meets them in the set-up's time, not after the end's estimate.
    reads = _as_carving_reads(scene)  # summed once for the three checks
    floor_note = _floor_note(scene, model.summary(), truth, reads)
    signal = _signal(scene, config, reads)
    return_ranges = _return_ranges(reads)
    far_note = far_views_warning(scene.sensor, return_ranges)
    ambient = _ambient(scene, return_ranges, reads[2])
    del reads  # not held through training: at 10,000 views of nine zones it is a hundred megabytes
    ring_note = _ring_note(scene)
    if budget_s is not None:
        _probe_end_costs(model, scene.n_views, truth, costs, clock, scene=scene)
        end_s = costs.end_s(config.mesh_resolution, config.metrics_points if truth else None, checkpoint_cost)
    plan = RunPlan(steps=run.plan.steps, budget_s=training_budget(run_clock, end_s), seed=run.plan.seed)
    if budget_s is not None and run_clock.left() <= 0:
        log(_spent_at_set_up(run_clock.elapsed(), budget_s, preset, dev.type))

    # The least the stages after training can take: the coarsest mesh, the fewest points, the pictures.
    min_end = costs.end_s(MIN_MESH_RESOLUTION, MIN_METRIC_POINTS if truth else None)
    governor = None
    if dev.type == "cpu" and not threads_fixed(threads, os.environ) and torch.get_num_threads() > 1:
        governor = ThreadGovernor(torch.get_num_threads(), torch.set_num_threads)
    # What the steps lost to other processes, on a CPU only: a GPU run waits for its device, not for a core.
    waits = ThreadWaits(thread_reader) if dev.type == "cpu" and thread_reader is not None else None
    evaluate = None
    if truth is not None:
        evaluate = lambda: _checkpoint_metrics(model, truth, config)  # noqa: E731
    result = train(model, plan, checkpoints=config.trace_checkpoints, evaluate=evaluate, progress=progress,
                   desc=f"reconstruct ({preset})", score_note=f"checkpoint {checkpoint_scoring(config, short=True)}",
                   early_stop=config.early_stop, on_step=None if governor is None else governor.step_done,
                   clock=clock, cpu_clock=cpu_clock,
                   eval_estimate_s=0.0 if checkpoint_cost is None else costs.checkpoint_s(*checkpoint_cost),
                   end_evaluation=None if budget_s is None else lambda seconds: seconds <= run_clock.left() - min_end,
                   stop=stop, waits=waits)
    stages = {"set_up_s": run_clock.elapsed() - result.seconds - result.eval_seconds}
    chosen = {}
    if after_training is not None:
        t_choose = clock()
        chosen = dict(after_training(model) or {})
        stages["after_training_s"] = clock() - t_choose
    t_end = clock()

    notes: list[str] = []
    resolution = mesh_resolution_within(costs, config.mesh_resolution,
                                        run_clock.left() - costs.pictures_s() - (costs.metrics_s(MIN_METRIC_POINTS)
                                                                            if truth else 0.0))
    if resolution < config.mesh_resolution:
        notes.append(f"the time budget was short: the mesh was extracted at {resolution} cells a side, not "
                     f"{config.mesh_resolution}")
    log(f"extracting the mesh ({resolution} cells a side)")
    try:
        mesh = model.extract_mesh(resolution)
    except ReconstructionError as exc:
        causes = [ring_note, far_note, ambient_warning(ambient)]  # what the capture alone says of its views and light
        raise ReconstructionError(_with_causes(str(exc), signal, causes)) from None
    export_mesh(mesh, out / "mesh.ply", vertex_normal=True)
    stages["mesh_s"] = clock() - t_end
    report = _report(capture, preset, dev, config, scene, model, result, plan, scored=truth is not None)
    report.update(chosen)
    report["capture_state"] = scene.state
    report["mesh_resolution"] = resolution
    if run.state_note:
        report["capture_note"] = run.state_note
    # The pictures before the metrics: what they take is kept back as a loaded machine's figure (FIXED_S), and on an
    # idle one most of it is left over; drawn first, that time goes to the metric points instead of being lost.
    log("pictures and report")
    t_pictures = clock()
    want = min(NOISE_VIEWS, scene.n_views)
    # The fit check's views, as many as the budget leaves once the fixed pictures and the fewest metric points are
    # kept back (a deterministic model renders each once; the paper preset's full-size render takes half a minute).
    fit_views = want if budget_s is None else fit_views_within(
        costs, want, fit_renders(model), run_clock.left() - costs.fixed_s - SAFETY * costs.coverage_s
        - (costs.metrics_s(MIN_METRIC_POINTS) if truth else 0.0), least=min(FIT_VIEWS, want))
    if fit_views < want:
        notes.append(f"the time budget was short: the fit was checked on {fit_views} views, not {want}")
    fit, no_preview = _pictures(out, mesh, None if truth is None else truth.mesh, model, scene, result, config,
                                fit_views)
    # The picture after the count of the views that see the mesh, which the report needs whatever the time.
    picture = coverage_picture_within(costs, run_clock.left() - SAFETY * costs.coverage_s, scored=truth is not None)
    if not picture:
        notes.append("the time budget was short: no coverage picture (coverage.png)")
    coverage = _coverage(out if picture else None, mesh, scene, log)
    pieces = _pieces(mesh, log)
    stages["pictures_s"] = clock() - t_pictures
    t_lost = clock()
    summary = model.summary()  # the trained model's, for the lost returns and the end's checks
    lost = _lost(mesh, scene, summary, log)
    stages["lost_returns_s"] = clock() - t_lost
    truth_note = None  # what the ground truth's fit with the mesh says, where there is one
    if truth is not None:
        # all that is left to draw after the metrics
        costs.fixed_s, costs.fit_check_s, costs.coverage_s = NORMALS_PICTURE_S, 0.0, 0.0
        t_metrics = clock()
        scored = truth.scored(mesh)  # cut once for the metrics and the normals picture
        points = metric_points_within(costs, config.metrics_points, run_clock.left() - costs.fixed_s)
        log(f"metrics against the ground truth ({points:,} points per mesh)")
        if truth.note():
            log(f"scoring {truth.note()}")
        report.update(truth.report_fields())
        vertex_err = pictures.vertex_normal_error_deg(scored, truth.mesh, n_gt=points)
        report["vertex_normal_error_deg"] = {"mean": float(vertex_err.mean()),
                                             "median": float(np.median(vertex_err))}
        # The points' distances measured until what the normals picture needs is all that is left: a forecast of
        # their time can fall short by seconds on a poor mesh, the deadline cannot. Without a budget: UNBUDGETED_S.
        deadline = clock() + (UNBUDGETED_S if budget_s is None else run_clock.left() - NORMALS_PICTURE_S)
        # The points are drawn from the metrics' own fixed seed, not the run's: `spadscan eval` of the mesh, a
        # baseline's figure and a run of another seed are scored on the same samples (docs/metrics.md).
        scores = mesh_metrics(scored, truth.mesh, n_points=points, deadline=deadline, clock=clock)
        if scores.queries < points and budget_s is None:
            notes.append(f"the metrics measured {scores.queries:,} of the {points:,} points per mesh in "
                         f"{UNBUDGETED_S:g} s, the most a run without a time budget gives them (a coarser estimate): "
                         f"likely the mesh and its ground truth lie far apart (is the ground truth the scanned "
                         f"object's, in metres?), or many points on a busy machine")
        elif scores.queries < points:  # one line for both cuts: this one says what the first did
            asked = f", {config.metrics_points:,} asked" if points < config.metrics_points else ""
            notes.append(f"the time budget was short: the metrics measured {scores.queries:,} of the {points:,} "
                         f"points per mesh{asked} (a coarser estimate)")
        elif points < config.metrics_points:
            notes.append(f"the time budget was short: the metrics used {points:,} points per mesh, not "
                         f"{config.metrics_points:,} (a coarser estimate)")
        truth_note = truth.mismatch_warning(scored, gt)
        figures = scores.to_dict()
        figures["metrics_seed"] = figures.pop("seed")  # "seed" stays the run's
        report.update(figures)
        report["chamfer_scoring"] = final_scoring(config, resolution, points, measured=scores.queries)
        pictures.normals_png(scored, vertex_err, out / "normals.png")
        report["ground_truth"] = str(gt)
        stages["metrics_s"] = clock() - t_metrics
    truth_pieces = None if truth is None else _truth_pieces(truth.mesh)
    small_note = _small_note(mesh, scene.sensor, return_ranges)
    if small_note:  # it says why the views were too far for this object, and how near to come: the far line's advice
        far_note = None
    top = _top(mesh, scene)
    top_note = top_warning(top)
    gap = floor_gap(np.asarray(mesh.vertices), summary.get("floor_z_m"), summary.get("floor"))
    gap_note = gap_warning(gap)
    facts = RunFacts(stopped_by=result.stopped_by, steps=result.steps,
                     model_converged=_model_converged(result.last), data_terms=result.data_terms,
                     device=dev.type, cpu_seconds=result.cpu_seconds, wall_seconds=result.seconds, fit=fit,
                     measured=bool(scene.real), budget_notes=notes,
                     scene_notes=[n for n in (run.counts_note, scene.bound_note, scene.pulse_note, floor_note,
                                              ring_note, far_note, small_note, top_note, gap_note,
                                              run.state_note,
                                              truth_note) if n],
                     coverage=coverage, pieces=pieces, signal=signal, lost=lost,
                     truth_pieces=None if truth_pieces is None else truth_pieces.count,
                     truth_tunnels=None if truth_pieces is None else truth_pieces.tunnels,
                     budget_s=budget_s, elapsed_s=run_clock.elapsed(),
                     continued=bool(getattr(model, "warm_started", False)), polish=polish,
                     training_s=result.seconds + result.eval_seconds, training_budget_s=plan.budget_s,
                     preset=config.preset, cuda_seen=torch.cuda.is_available(),
                     thread_times=None if waits is None else waits.summary(), machine_jobs=siblings,
                     threads_fixed=threads_fixed(threads, os.environ), dark=_dark(summary),
                     thin_sheets_emptied=_part_figure(summary, "thin_sheets", "emptied_nodes"), ambient=ambient)
    report["converged"] = end_of_run.converged(facts)
    report["warnings"] = end_of_run.warnings(facts) + ([threads_note] if threads_note else [])
    report["fit_to_noise"] = None if fit is None else fit.to_dict()
    report["coverage"] = None if coverage is None else coverage.to_dict()
    report["pieces"] = None if pieces is None else pieces.to_dict()
    if report["pieces"] is not None and truth_pieces is not None:
        report["pieces"]["truth_tunnels"] = truth_pieces.tunnels
    report["signal"] = None if signal is None else signal.to_dict()
    report["lost_returns"] = None if lost is None else lost.to_dict()
    report["ambient_light"] = None if ambient is None else ambient.to_dict()
    report["top_reach"] = None if top is None else top.to_dict()
    report["floor_gap"] = None if gap is None else gap.to_dict()
    report["cpu_cores_used"] = end_of_run.cpu_share(facts)
    report["cpu_wait"] = end_of_run.cpu_wait(facts)
    report["machine_jobs"] = siblings
    report["threads"] = (governor.summary() if governor is not None else
                         {"fixed": torch.get_num_threads()} if dev.type == "cpu" else None)
    report["budget"] = {"budget_s": budget_s, "training_budget_s": plan.budget_s,
                        "end_estimate_s": end_s, "timed": costs.probed, "notes": notes,
                        "stages": stages}
    for line in report["warnings"]:
        if line not in (run.counts_note, run.state_note, threads_note):  # said already, as the run started
            log(f"warning: {line}")
    if no_preview is not None:  # after the log's warnings: said on stderr already, as the 3D view's is
        report["warnings"] = [*report["warnings"], no_preview]
    ensure_view3d(report, out)  # before the files are listed: a view that cannot be made leaves no stale one
    written = files_written_after(out, before) | {"report.json", "report.html"}
    report["files"] = sorted(written)
    report["wall_seconds"] = run_clock.elapsed()
    write_report(out, report)
    report = json_safe(report)
    write_report_html(report, out)
    return report


def threads_warning(threads: int, cores: int) -> str | None:
    """The line saying that `threads` CPU threads (`--threads`) are more than the machine's `cores`, or None: OpenMP
    threads that lose their core stall each other. One of the run's warnings: its steps, and so its result within a
    time budget, suffer from it."""
    if threads <= cores:
        return None
    return (f"{threads} CPU threads on {cores} cores: OpenMP threads that lose their core stall each other, each "
            f"step many times slower (--threads {cores} or fewer)")


FLOOR_WHY = {"config": "field.floor_z, by default z = 0, where simulated scenes stand",
             "capture": "the capture's scene.floor_z"}
"""Why a fit has a floor that is no table, by the fast preset's `floor` note (a table the fit found or was given
is seen in the histograms: no warning)."""
FLOOR_REMEDY = {"config": "--set field.floor_z=null takes the floor away, --set field.floor_z=HEIGHT (metres) moves it",
                "capture": "change or remove scene.floor_z in the capture's scan.json"}


def _floor_note(scene: SceneData, summary: dict, truth, reads: tuple) -> str | None:
    """The warning that the floor the fit assumes (not a table) cuts the object, or None: first returns that only
    surface below it can have given, or with a ground truth, a share of its surface below it (docs/end_of_run.md).
    `summary`: the model's summary (the fast preset names its floor and where it comes from; the paper preset has
    none). `reads`: the scene as carving reads it (`_as_carving_reads`)."""
    floor_z, source = summary.get("floor_z_m"), summary.get("floor")
    if not isinstance(floor_z, (int, float)) or source not in FLOOR_WHY:
        return None
    counts, sensor, usable = reads
    below = returns_below_floor(counts, scene.poses.double().cpu().numpy(), sensor, float(floor_z), usable)
    share = None if truth is None else mesh_share_below(truth.mesh, float(floor_z))
    return floor_cut_note(float(floor_z), FLOOR_WHY[source], below, share, FLOOR_REMEDY[source])


def _warn_long_default(config: ReconConfig, dev: torch.device, steps, budget_s, log) -> None:
    if budget_s is None and dev.type == "cpu" and (steps or 0) >= LONG_CPU_STEPS:
        log(f"warning: preset {config.preset!r} runs {steps:,} steps by default: days on a CPU (--budget-s or "
            f"--steps to bound it)")


def _model_converged(last: dict) -> bool | None:
    """The model's own convergence test at its last step, or None when it reports none (the paper preset)."""
    value = (last or {}).get("converged")
    return None if value is None else bool(value)


def _probe_end_costs(model, n_views: int, truth, costs: EndCosts, clock, scene: SceneData | None = None) -> None:
    """Time a small mesh extraction, the render of two views (the fit check renders up to NOISE_VIEWS views
    NOISE_RENDERS times), with `scene` the coverage count on that mesh (`_probe_coverage`) and with a ground truth
    small metrics, on this model and machine, so that the budget keeps back what the end of the run will take here.
    A short probe is timed twice, the faster kept (probe_seconds)."""
    if scene is not None:  # the default, where no probe times it, is for the views the report counts
        spread, others = counted_views(*_poses_usable(scene))
        costs.coverage_views(len(spread), others)
    probe_views = sorted({0, n_views // 2})
    seconds, _ = probe_seconds(partial(model.render_histograms, probe_views), clock)
    costs.time_fit_check(seconds, len(probe_views), min(NOISE_VIEWS, n_views) * fit_renders(model))
    timings = {}
    try:
        for resolution in PROBE_RESOLUTIONS:
            timings[resolution], mesh = probe_seconds(partial(model.extract_mesh, resolution), clock)
    except SpadscanError:  # no surface yet: the default rates stand
        return
    costs.time_mesh(timings)
    if scene is not None:
        _probe_coverage(mesh, scene, costs, clock)
    if truth is not None:
        try:
            seconds, _ = probe_seconds(partial(truth.metrics, mesh, n_points=PROBE_POINTS), clock)
        except SpadscanError:
            return
        costs.time_metrics(PROBE_POINTS, seconds)


def _probe_coverage(mesh, scene: SceneData, costs: EndCosts, clock) -> None:
    """Time the count of the views that see each sample point (`_coverage`) on `mesh`, over COVERAGE_PROBE_VIEWS of
    the views the report's count reads for every point (spread among them), so that the budget keeps back that count
    as the report makes it: of a large capture, on its spread views, not on every view (coverage.spread_counts). A
    mesh without surface leaves the default (EndCosts.coverage_views, set by `_probe_end_costs`)."""
    poses, usable = _poses_usable(scene)
    spread, others = counted_views(poses, usable)
    timed = spread[spread_views(poses[spread], COVERAGE_PROBE_VIEWS, None if usable is None else usable[spread])]
    count = partial(surface_views, mesh, poses[timed], scene.sensor, usable=None if usable is None else usable[timed])
    try:
        seconds, samples = probe_seconds(count, clock)
    except SpadscanError:
        return
    # The other views are counted only for the points the spread views see fewer than FEW_VIEWS times: the probe's
    # counts estimate what share that is (coverage.few_share; a flat plate seen close up: all).
    costs.time_coverage(seconds, len(timed), len(spread), others, few_share(samples.counts, len(timed), len(spread)))


def _ring_note(scene: SceneData) -> str | None:
    """The warning that every view stands at one elevation about the scene's centre, else that every view looks down
    from above only, else that every view stands low down (view_spread.py), or None."""
    poses, usable = _poses_usable(scene)
    spread = view_elevations_deg(poses, scene.center.double().cpu().numpy(), usable)
    return one_ring_warning(*spread) or above_only_warning(*spread) or low_only_warning(*spread)


def _return_ranges(reads: tuple) -> np.ndarray:
    """(n,) range (metres) of the first return of each histogram that holds one, as carving finds them
    (`carving.returns.first_returns`, its matched filter at its default level) in the scene as carving reads it
    (`reads`: `_as_carving_reads`, its frames summed): where the object lies from the views, for the checks on their
    distance (view_spread.py) and on the ambient light. The matched filter finds a small object's faint returns that
    a histogram's highest bin misses (a 5 cm ball from 0.6 m: 24 of 24 views against 1), and under bright ambient
    light the object's return, where the highest bin lies early (pile-up piles the background there)."""
    counts, sensor, usable = reads
    found = detected_returns(counts, sensor, DEFAULT_THRESHOLD, usable=usable)
    return np.asarray(sensor.range_of_bin(found.arrival_bin[found.detected]), np.float64)


def _ambient(scene: SceneData, ranges: np.ndarray, usable: np.ndarray | None) -> Ambient | None:
    """How much of the laser cycles ambient light stopped before the object's returns (ambient_light.py): the fit's
    own background, at the bins of the first returns (`ranges`, metres: `_return_ranges`), over the histograms with
    data (`usable` (V, Z) bool, as `_as_carving_reads` gives it; None for all)."""
    return capture_ambient(scene.background.double().cpu().numpy(), scene.cycles.double().cpu().numpy(),
                           scene.sensor.bin_of_range(ranges), bool(scene.sensor.pileup), usable)


def _small_note(mesh, sensor, ranges: np.ndarray) -> str | None:
    """The warning that one zone sees a patch several times the mesh's size at the views' returns (`ranges`, metres:
    `_return_ranges`; view_spread.py), or None (None too for a mesh without vertices)."""
    vertices = np.asarray(mesh.vertices)
    if not len(vertices):
        return None
    return small_object_warning(sensor, ranges, float(np.ptp(vertices, axis=0).max()))


def _top(mesh, scene: SceneData) -> TopReach | None:
    """Whether the views looked above the mesh's top (top_reach.py), or None for a mesh without vertices."""
    poses, usable = _poses_usable(scene)
    return top_reach(np.asarray(mesh.vertices), poses, scene.sensor, usable)


def _as_carving_reads(scene: SceneData) -> tuple[np.ndarray, object, np.ndarray | None]:
    """(counts (V, Z, B) float64, sensor, usable (V, Z) bool or None) of the scene as carving reads them: each view's
    frames summed into one histogram (`carving.views.summed_views`), the histograms without data marked."""
    counts, sensor = summed_by_cycles(scene.counts.double().cpu().numpy(), scene.cycles.double().cpu().numpy(),
                                      scene.sensor)
    return counts, sensor, None if scene.usable is None else scene.usable.cpu().numpy()


def _poses_usable(scene: SceneData) -> tuple[np.ndarray, np.ndarray | None]:
    """(poses (V, 4, 4) float64, usable (V, Z) bool or None) of the scene as numpy: what the coverage count reads."""
    usable = getattr(scene, "usable", None)  # (V, Z): dropped frames saw nothing
    return scene.poses.detach().double().cpu().numpy(), None if usable is None else usable.cpu().numpy()


def checkpoint_scoring(config: ReconConfig, short: bool = False) -> str:
    """How checkpoints are scored, for every place their Chamfer is shown: coarser than the final mesh. short: no
    commas (for the progress bar's fields)."""
    points = f"{config.trace_points / 1000:g}k" if short and config.trace_points >= 1000 else f"{config.trace_points:,}"
    return f"{config.trace_mesh_resolution}-cell mesh{';' if short else ','} {points} points"


def final_scoring(config: ReconConfig, resolution: int | None = None, points: int | None = None,
                  measured: int | None = None) -> str:
    """How the final mesh is scored (the summary's Chamfer): its resolution and points (default: the config's), and
    `measured`, the points the metrics' deadline left measured, where fewer ('15,000 of 286,000 points'): the figure
    rests on those alone."""
    points = points or config.metrics_points
    some = f"{measured:,} of " if measured is not None and measured < points else ""
    return f"final {resolution or config.mesh_resolution}-cell mesh, {some}{points:,} points"


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
                     f"{config.trace_mesh_resolution}-cell marching-cubes grid, the final metrics up to "
                     f"{config.metrics_points} points on up to {config.mesh_resolution} cells (n_points, queries "
                     f"and mesh_resolution: what they used)")
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


def _coverage(out: Path | None, mesh, scene: SceneData, log) -> Coverage | None:
    """How many views saw each part of the mesh (coverage.py), and with `out` coverage.png there, the mesh coloured
    by it; None (said in the log) where it cannot be measured."""
    try:
        poses, usable = _poses_usable(scene)
        samples = surface_views(mesh, poses, scene.sensor, usable=usable)
        if out is not None:
            # The legend's shares are the report's: of the surface less its undersides, which no view above sees.
            pictures.coverage_png(mesh, vertex_views(mesh, samples), out / "coverage.png", few_views=FEW_VIEWS,
                                  area_views=samples.counts[~samples.underside])
        return summarize(samples)
    except SpadscanError as exc:
        log(f"no coverage measured: {exc}")
        return None


def _pieces(mesh, log) -> Pieces | None:
    """The mesh's connected pieces (pieces.py), or None (said in the log) for a mesh without surface."""
    try:
        return mesh_pieces(mesh)
    except SpadscanError as exc:
        log(f"no pieces counted: {exc}")
        return None


def _part_figure(summary: dict, part: str, key: str):
    """A figure of a fast preset's part's summary, or None where the part did not run (or the preset has none)."""
    return ((summary.get("parts") or {}).get(part) or {}).get(key)


def _dark(summary: dict) -> dict | None:
    """The dark-restart part's summary with the fitted albedo (`RunFacts.dark`), or None where it did not run."""
    part = (summary.get("parts") or {}).get("dark_restart")
    return None if part is None else {**part, "albedo": summary.get("albedo")}


def _lost(mesh, scene: SceneData, summary: dict, log) -> LostReturns | None:
    """The first returns the mesh does not account for (lost_returns.py), read as carving reads the histograms
    (frames summed, those without data left out), with the table the object stood on: the plane the fit ended with
    (the fast preset's summary of its table part), else the scene's as the capture set it up; None (said in the log)
    where they cannot be judged."""
    counts, sensor, usable = _as_carving_reads(scene)
    poses = _poses_usable(scene)[0]
    table = None
    if scene.table is not None:
        fitted = ((summary.get("parts") or {}).get("table")) or {}
        if isinstance(fitted.get("table_offset_m"), (int, float)) and fitted.get("table_normal") is not None:
            table = (np.asarray(fitted["table_normal"], np.float64), float(fitted["table_offset_m"]))
        else:
            table = (np.asarray(scene.table.normal, np.float64), float(scene.table.offset))
    try:
        return lost_returns(counts, poses, sensor, mesh, scene.center.double().cpu().numpy(), scene.radius, table,
                            usable, measured=bool(scene.real))
    except SpadscanError as exc:
        log(f"no returns held against the mesh: {exc}")
        return None


def _truth_pieces(mesh) -> Pieces | None:
    """The ground truth's pieces (of note, and the tunnels through them), counted as the result's are, or None for
    one without surface."""
    try:
        return mesh_pieces(mesh)
    except SpadscanError:
        return None


def _with_causes(error: str, signal: Signal | None, capture_notes: list[str | None]) -> str:
    """A run's error, with what the checks that need only the capture found after it: its signal check (`signal`,
    measured before training) where that finds too little signal, and `capture_notes`, the lines on its views and
    its light (None where they say nothing). A capture too faint can leave the fit no surface at all (a dim torus at
    four times the ambient light), and so can views that see the object only at a grazing angle (a flat plate seen
    from 25 degrees up at most); these name the cause and what to do."""
    lines = [line for line in (signal_warning(signal), *capture_notes) if line]
    return "; ".join([error, *lines])


def _signal(scene: SceneData, config: ReconConfig, reads: tuple) -> Signal | None:
    """The aimed zone's histograms with no return at carving's level, read as carving reads them (`reads`:
    `_as_carving_reads`: frames summed, histograms without data left out; the weak threshold off a table); None for a
    preset that does not carve (the paper preset)."""
    threshold = getattr(config.field, "carve_threshold", None)
    if threshold is None:
        return None
    counts, sensor, usable = reads
    on_table = scene.table is not None
    # Carving's thresholds as shipped: a capture too faint at their level stays faint when the level is lowered.
    return capture_signal(counts, sensor, float(threshold), usable,
                          weak_threshold=carve_weak_threshold(config.field, on_table=on_table),
                          defaults=default_thresholds(config.field, on_table=on_table))


def fit_renders(model) -> int:
    """Renders of each fit-check view: NOISE_RENDERS, averaged, for a model that renders randomly sampled rays; one
    for a model whose render is deterministic (`stochastic_render = False`: the same render again would add
    nothing and cost as much)."""
    return NOISE_RENDERS if getattr(model, "stochastic_render", True) else 1


def _pictures(out: Path, mesh, gt_mesh, model, scene, result, config: ReconConfig,
              n_views: int) -> tuple[FitNoise | None, str | None]:
    """preview.png, error_vs_time.png and fit.png; returns the fit against the photon noise on `n_views` views
    spread over the capture, those the fit picture shows among them (end_of_run.fit_noise; each rendered
    `fit_renders` times and averaged, the spread of the renders giving the renderer's own sampling noise, which the
    check counts with the photon noise), and the report's warning where the preview was not drawn (None where it
    was)."""
    no_preview = pictures.preview_or_warning(mesh, out / "preview.png", gt=gt_mesh)
    # how the checkpoints' Chamfer was scored, where the picture shows one (a run whose budget left them unscored
    # plots the loss alone, and its title says so)
    scored = gt_mesh is not None and pictures.chamfer_points(result.trace)
    scoring = f" (checkpoint Chamfer: {checkpoint_scoring(config)})" if scored else ""
    pictures.error_vs_time_png(result.trace, out / "error_vs_time.png",
                               title=f"{config.preset}: error against run time{scoring}")
    views = sorted({int(round(i)) for i in np.linspace(0, scene.n_views - 1, n_views)})
    renders = np.stack([model.render_histograms(views) for _ in range(fit_renders(model))])
    rendered = renders.mean(axis=0)
    measured = scene.counts[views].double().cpu().numpy()
    shown = sorted({int(round(i)) for i in np.linspace(0, len(views) - 1, min(FIT_VIEWS, len(views)))})
    pictures.fit_png(measured[shown], rendered[shown], [views[i] for i in shown], out / "fit.png")
    return fit_noise(measured, rendered, scene.valid[views].cpu().numpy(), views,
                     expected_var=renders.var(axis=0, ddof=1) / len(renders) if len(renders) > 1 else None), no_preview
