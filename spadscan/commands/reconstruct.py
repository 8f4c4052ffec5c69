"""Reconstruct one capture into a mesh and a report, by differentiable rendering of its histograms.

Writes into --out (a new folder, or one without a result unless --overwrite): report.html (the page to open first),
mesh.ply (per-vertex normals from the SDF gradient), report.json (preset, device, steps, training seconds, the model
terms used, final loss, the resolved config, and with a ground truth: chamfer_mm, accuracy_mm, completeness_mm,
fscore_5mm, normal_error_deg plus a trace of error against training time), preview.png, error_vs_time.png, fit.png
(measured against rendered histograms) and, with a ground truth, normals.png (per-vertex normal error). Without --gt,
the ground truth that the capture names is used (import-lcspc and simulate record theirs); --no-gt skips the metrics.
The run stops at --steps or --budget-s, whichever comes first; with neither, the preset's default (fast: 120 s of
training; paper: 300,000 steps, hours on a GPU and days on a CPU). The `fast` preset also stops early once its data
term has stopped improving (report.json: stopped_by 'converged'); turn that off with --set early_stop=false.

Presets: `fast` (default) is an SDF grid that reaches good meshes in minutes on a CPU; `paper` is the published
method (an MLP SDF, 300K steps nominal: hours on a GPU). The `fast` preset's mechanisms are parts (refinement,
hull_projection, table, cavities, thin_sheets, coarse_smoothing, openings, erosion, blur, empty_space, average,
plateau), each with its settings under parts.NAME; report.json's model.parts lists those that ran with their
settings, and model.parts_left_out why the others did not (switched off, or not for this scene). Switch one off
with --set parts.NAME.enabled=false.

The progress bar's Chamfer is the last checkpoint's, scored on a coarser mesh with fewer points than the final
figure (fast: 128 cells and 30,000 points against 256 cells and 300,000), so it reads higher than the summary line's;
both say how they were scored.

Examples:
  spadscan reconstruct captures/bunny --out results/bunny --budget-s 180 --gt bunny.obj
  spadscan reconstruct captures/bunny --out results/bunny-paper --preset paper --steps 20000 --device cuda
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from spadscan.worker.ground_truth import add_ground_truth_options, ground_truth_for_run
from spadscan.worker.outputs import check_out
from spadscan.worker.recon.config import PRESET_NAMES, parse_override


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", metavar="CAPTURE", help="capture folder (holds scan.json)")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder for the mesh, report and pictures")
    parser.add_argument("--preset", default="fast", choices=PRESET_NAMES,
                        help="reconstruction method (default: fast)")
    parser.add_argument("--budget-s", type=float, default=None, metavar="S",
                        help="stop after S seconds of training, checkpoint scoring included (the set-up before it, "
                             "and the final mesh, metrics and pictures after it, are not counted)")
    parser.add_argument("--steps", type=int, default=None, metavar="N", help="stop after N optimisation steps")
    add_ground_truth_options(parser, ", for the metrics")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                        help="where to compute (default: auto = CUDA when available)")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default: 0)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                        help="override a field of the preset's config, e.g. --set field.resolution=48, or switch "
                             "one of the fast preset's parts off: --set parts.openings.enabled=false (repeatable; "
                             "the resolved config and the parts that ran are saved in report.json)")
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="CPU threads (default: OMP_NUM_THREADS if set, else torch's choice, the cores); with "
                             "other reconstructions running at once, share the cores out: threads that outnumber "
                             "the cores make every step many times slower")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the result already in --out (without it, a folder that holds mesh.ply or "
                             "report.json is refused)")
    parser.add_argument("--no-progress", action="store_true", help="do not show a progress bar")


def run(args: argparse.Namespace) -> int:
    from spadscan.worker.reconstruct import reconstruct_capture  # torch: only when a reconstruction runs

    out = check_out(args.out, args.overwrite, capture=args.capture)
    overrides = dict(parse_override(text) for text in args.overrides)

    def log(line: str) -> None:
        print(f"spadscan reconstruct: {line}", file=sys.stderr, flush=True)

    gt = ground_truth_for_run(args.capture, args.gt, args.no_gt, log)
    report = reconstruct_capture(Path(args.capture), out, preset=args.preset, budget_s=args.budget_s,
                                 steps=args.steps, gt=gt, device=args.device, seed=args.seed,
                                 progress=not args.no_progress, overrides=overrides or None, threads=args.threads,
                                 log=log)
    steps = f"{report['steps']} step{'' if report['steps'] == 1 else 's'}"
    # Training time is what --budget-s bounds (with checkpoints); the wall time adds set-up, the mesh and the metrics.
    line = (f"{report['preset']}: {steps} in {report['seconds']:.1f} s of training ({report['wall_seconds']:.1f} s "
            f"in all) on {report['device']}, final loss {report['final_loss']:.4g}")
    if report.get("chamfer_mm") is not None:
        line += (f"; Chamfer {report['chamfer_mm']:.2f} mm ({report['chamfer_scoring']}; accuracy "
                 f"{report['accuracy_mm']:.2f}, completeness {report['completeness_mm']:.2f}), F-score@5mm "
                 f"{report['fscore_5mm']:.3f}, normal error (sampled points) {report['normal_error_deg']:.1f} deg")
    print(line)
    print(f"wrote {out / 'report.html'} (open this first), mesh.ply, report.json, preview.png, error_vs_time.png, "
          "fit.png")
    return 0
