"""Reconstruct one capture into a mesh and a report, by differentiable rendering of its histograms.

Writes into --out (a new folder, or one without a result unless --overwrite; the run writes into a hidden .tmp-
folder beside it, or inside it where its result could not be moved in from beside it (--out a mount point, a link to
another disk, in a folder you cannot write), and moves its result in once finished: a result that appeared in --out
meanwhile, a worker's, is kept unless --overwrite): report.html (the page to open first), view3d.html (the 3D view
report.html embeds: keep it beside report.html), mesh.ply (per-vertex normals from the SDF gradient), report.json
(preset, device, steps, training seconds, the model terms used, final loss, the resolved config, and with a ground
truth: chamfer_mm, accuracy_mm, completeness_mm, fscore_5mm, normal_error_deg plus a trace of error against training
time), preview.png, error_vs_time.png, fit.png (measured against rendered histograms), coverage.png (the mesh
coloured by how many views saw each part: red where none did, its shape a guess) and, with a ground truth,
normals.png (per-vertex normal error). Without --gt, the ground truth that the capture names is used (import-lcspc
and simulate record theirs); --no-gt skips the metrics. --budget-s bounds the whole run, from the command's start to
its report (within 10 % or 10 s, whichever is larger): loading the capture, training, the mesh, the metrics and the
pictures share it, and when time is short the mesh is coarser and the metrics use fewer points (report.json's
"budget" and "warnings" say so). --steps bounds the training steps; with neither, the preset's default (fast: a 120
s budget; paper: 300,000 steps, hours on a GPU and days on a CPU). The `fast` preset also stops early once its data
term has stopped improving (report.json: stopped_by 'converged'); turn that off with --set early_stop=false.

Stopping a run: a first Ctrl-C while it trains ends the training at its next step and keeps the run: the mesh, the
metrics and the report follow as after a budget (stopped_by 'interrupted'; its warnings say the fit was stopped
before it converged); a first one after training changes nothing, the mesh and report are made. A second Ctrl-C,
one before training began, or SIGTERM (a time limit, a service stop) aborts the run, keeping nothing: the hidden
folder is removed and --out is left as it was. A run started with Ctrl-C ignored (a shell script's background job)
keeps ignoring it. Exit status: 0 when a result was written (report.json's stopped_by says how its training
ended: converged, budget, steps, interrupted), 1 on an error (one line), 130 when aborted.

An honest end: report.json's "converged" says whether the fit had settled, and "warnings" (also printed, and shown
at the top of report.html) says why a result may be doubtful: a run that stopped on its budget or step count while
its fit was still improving, a run starved of CPU by other processes, a fit that does not explain the measurements
(a simulated capture: over 10 % of its histograms off the model beyond their photon noise and by over 15 %; a real
one: the model off by more than 60 % per bin, twice what a real sensor's own departures from its model leave), a
surface seen by too few views, a mesh in pieces (more than its ground truth has), specks holding more of the
surface than a good fit leaves, holes through thin walls (more tunnels than its ground truth has), too little
signal (the zone aimed at the object empty in many views, each carving its view away; with the carving thresholds
set lower, judged at their default level too: faint returns), a scene bound that cuts the object, a mesh or metrics
made coarser to fit the budget (docs/end_of_run.md).

CPU threads: without --threads (and without OMP_NUM_THREADS), a CPU run times its steps with all the cores' threads
and with one, keeps the faster and checks again from time to time, so that a busy machine does not make every step
many times slower; its OpenMP threads spin briefly before they sleep (GOMP_SPINCOUNT=30000: two threads then beat
one on idle cores). With --threads (or OMP_NUM_THREADS) the count is kept and the threads wait passively
(OMP_WAIT_POLICY=PASSIVE), so that a busy core does not stall them; a wait policy or spin count you set is kept.
report.json's "threads" says what it chose.

Presets: `fast` (default) is an SDF grid that reaches good meshes in minutes on a CPU; `paper` is the published
method (an MLP SDF, 300K steps nominal: hours on a GPU). The `fast` preset's mechanisms are parts (refinement,
hull_projection, table, cavities, thin_sheets, coarse_smoothing, openings, erosion, blur, unseen, empty_space,
average, plateau, dark_restart), each with its settings under parts.NAME; report.json's model.parts lists those
that ran with their settings, and model.parts_left_out why the others did not (switched off, or not for this
scene). Switch one off with --set parts.NAME.enabled=false.

Progress: on a terminal, a bar of the training. With --budget-s its seconds are training's share of the budget,
not the whole budget: the rest is kept for the set-up before it and the mesh, metrics and pictures after it (a 25 s
budget may show a bar of 10 s); with --steps alone it counts steps. Its Chamfer is the last checkpoint's, scored on a
coarser mesh with fewer points than the final figure (fast: 128 cells and 30,000 points against 256 cells and
300,000), so it reads higher than the summary line's; both say how they were scored. When standard error is a file
or a pipe (`2>run.log`, cron, systemd), the bar's readings come as plain lines instead, one each tenth of the
training and at least every 30 s (`reconstruct (fast): 4.0/10.0 s of training (40 %), step 120, loss 2.25 [00:05]`);
--progress draws the bar there too, --no-progress shows neither.

Examples:
  spadscan reconstruct captures/bunny --out results/bunny --budget-s 180 --gt bunny.obj
  spadscan reconstruct captures/bunny --out results/bunny-paper --preset paper --steps 20000 --device cuda
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from spadscan.cli import add_progress_options, progress_bar_wanted
from spadscan.protocol.errors import ConfigError
from spadscan.worker.ground_truth import add_ground_truth_options, ground_truth_for_run
from spadscan.worker.jobs import add_to_report, run_limits_problem
from spadscan.worker.outputs import check_ground_truth_kept, check_out
from spadscan.worker.publish_out import result_beside
from spadscan.worker.recon.config import PRESET_NAMES, parse_override, with_overrides


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", metavar="CAPTURE", help="capture folder (holds scan.json)")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder for the mesh, report and pictures")
    parser.add_argument("--preset", default="fast", choices=PRESET_NAMES,
                        help="reconstruction method (default: fast)")
    parser.add_argument("--budget-s", type=float, default=None, metavar="S",
                        help="bound the whole run to S seconds, from start to report: set-up, training, mesh, "
                             "metrics and pictures share it (the progress bar counts training's share alone); at "
                             "most a week (default: the preset's; fast: 120)")
    parser.add_argument("--steps", type=int, default=None, metavar="N",
                        help="stop after N optimisation steps, 1 to 10,000,000 (default: the preset's; fast: until it "
                             "converges or its time budget ends)")
    add_ground_truth_options(parser, ", for the metrics")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                        help="where to compute (default: auto = CUDA when available)")
    parser.add_argument("--seed", type=int, default=0, metavar="S",
                        help="the fit's random seed (default: 0). A run repeats to the last digit with the same seed, "
                             "steps and --threads; without --threads the threads chosen as it goes (which a busy "
                             "machine changes) move it by a few hundredths of a millimetre. The metrics draw their "
                             "points from their own fixed seed, as `spadscan eval` does")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                        help="override a field of the preset's config, e.g. --set field.resolution=48, or switch "
                             "one of the fast preset's parts off: --set parts.openings.enabled=false (repeatable; "
                             "the resolved config and the parts that ran are saved in report.json)")
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="CPU threads, kept for the whole run (default: OMP_NUM_THREADS if set; else the "
                             "cores' threads or one, whichever makes faster steps, chosen as the run goes); threads "
                             "that outnumber the cores make every step many times slower; give it to repeat a run "
                             "exactly")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the result already in --out: the files its report.json lists that this run "
                             "does not write again are removed, and, in a worker job's result (one that holds "
                             "its .complete marker or job.json), the job's job.json, job.log, ground_truth.ply and "
                             ".complete marker; other files are left (without it, a folder that "
                             "holds mesh.ply or report.json is refused)")
    add_progress_options(parser, "show no progress, neither bar nor lines",
                         "a plain line at each tenth of the training and at least every 30 s")


def run(args: argparse.Namespace) -> int:
    import os

    from spadscan.signals import first_interrupt_stops_training, terminate_as_interrupt
    from spadscan.worker.budget import process_started
    from spadscan.worker.threads import check_threads, threads_fixed, wait_env

    started = process_started()  # the budget counts from here: torch's import and the set-up are part of the run
    # The options first, the files and folders they name after (a --out that holds a result, a capture that is none):
    # fixing one error must not reveal another that was there all along. The run's limits, named by their flags,
    # before anything is said or imported (the library's check names none).
    problem = run_limits_problem(args.budget_s, args.steps, args.seed, flags=True)
    if problem:
        raise ConfigError(problem)
    if args.threads is not None:
        check_threads(args.threads)
    overrides = dict(parse_override(text) for text in args.overrides)
    # Read once, when torch's OpenMP runtime starts: before it.
    os.environ.update(wait_env(os.environ, adapting=not threads_fixed(args.threads, os.environ)))
    from spadscan.worker.recon.trainer import PROGRESS_LINES
    from spadscan.worker.reconstruct import reconstruct_capture  # torch: only when a reconstruction runs

    if overrides:  # each --set against the preset's config, as the run will
        from spadscan.worker.recon.presets import preset_config

        with_overrides(preset_config(args.preset), overrides)
    out = check_out(args.out, args.overwrite, capture=args.capture)  # --out too, as it is, not its scratch folder

    def log(line: str) -> None:
        say(f"spadscan reconstruct: {line}")

    gt, gt_note = ground_truth_for_run(args.capture, args.gt, args.no_gt, log)
    if args.overwrite:
        check_ground_truth_kept(gt, out)
    # SIGTERM (a time limit, a service stop) aborts: the scratch folder is removed, --out left as it was. A first
    # Ctrl-C while training ends the training and keeps the run; a second aborts as SIGTERM does.
    def said_over_the_bar(line: str) -> None:
        # A Ctrl-C comes while the bar is drawn: its line starts a line of its own, not glued to the bar's end.
        say(f"\nspadscan reconstruct: {line}")

    bar = progress_bar_wanted(args)
    progress = True if bar else (False if args.no_progress else PROGRESS_LINES)  # lines: what a log wants
    with (terminate_as_interrupt(),
          first_interrupt_stops_training(said_over_the_bar if bar else log) as stop,
          result_beside(out, args.overwrite, log) as scratch):  # published whole at the end
        report = reconstruct_capture(Path(args.capture), scratch, preset=args.preset, budget_s=args.budget_s,
                                     steps=args.steps, gt=gt, device=args.device, seed=args.seed,
                                     progress=progress, overrides=overrides or None,
                                     threads=args.threads, log=log, started=started, stop=stop)
        if gt_note:  # the page says why it has no metrics, as a worker's job's does
            add_to_report(scratch, {"ground_truth_note": gt_note})
    steps = f"{report['steps']} step{'' if report['steps'] == 1 else 's'}"
    converged = "converged" if report.get("converged") else "not converged"
    line = (f"{report['preset']}: {steps} in {report['seconds']:.1f} s of training ({report['wall_seconds']:.1f} s "
            f"in all) on {report['device']}, {converged}, final loss {report['final_loss']:.4g}")
    if report.get("chamfer_mm") is not None:
        line += (f"; Chamfer {report['chamfer_mm']:.2f} mm ({report['chamfer_scoring']}; accuracy "
                 f"{report['accuracy_mm']:.2f}, completeness {report['completeness_mm']:.2f}), F-score@5mm "
                 f"{report['fscore_5mm']:.3f}, normal error (sampled points) {report['normal_error_deg']:.1f} deg")
    print(line)
    written = [str(name) for name in report.get("files") or () if name != "report.html"]
    print(f"wrote {out / 'report.html'} (open this first), " + ", ".join(written))
    return 0


def say(text: str) -> None:
    """A line on stderr, where a reader that went away (`... 2>&1 | head`, a closed log) does not end the run: its
    result is still published (report.json keeps what the lines said)."""
    try:
        print(text, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass
