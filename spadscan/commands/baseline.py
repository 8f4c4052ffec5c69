"""Run one of the paper's baselines on a capture: reprojection or space carving (numpy, no torch).

reprojection   each zone's first return, back-projected along the zone's axis, gives one point (none for a return
               at zero or negative range); the points are saved as DIR/points.ply and a surface is built from them
               (--surface).
space-carving  voxels that a zone saw as empty (in its field of view, in front of its first return) are carved;
               what is left is the hull, meshed by marching cubes.

The detection threshold T is a z-score: a bin holds a return when the pulse-filtered, background-free signal
exceeds T standard deviations of the background noise (pile-up undone first). Both methods filter with the pulse's
leading edge, whose response does not reach far ahead of a return: filtered with the whole pulse, a long-tailed pulse
(the TMF8820's) lifts background-only bins up to 35 cm in front of a strong return over the threshold. Histograms
that no sensor could have produced (the "left out" warning) give no return, and stay out of the crosstalk
unmixing, where they would move the other zones of their view. Without --threshold, T is the sensor's default: 20
on a TMF8820 (at 5, noise clears it in zones that see nothing and space carving's hull grew to a metre), 5 on
others. --calibrate tries thresholds from 3 to 300 and keeps the one with the lowest Chamfer distance to the ground
truth, as the paper did (and says so in the report; a warning when the best is the lowest or highest tried, since a
threshold beyond it may do better). A carved hull wider than 1.5 times the box its first returns lie in is called
implausible, in one warning line on the terminal and in the report (report.json's implausible_hull). Without
--gt, the ground truth that the capture names is used (import-lcspc and simulate record theirs); --no-gt skips it.
Writes into DIR (a new folder, or one without a result unless --overwrite): report.html (the page to open first),
view3d.html (the 3D view report.html embeds: keep it beside report.html), mesh.ply, report.json (method, threshold
and threshold_source, calibrated, seconds, warnings, and with a ground truth the metrics: chamfer_mm, accuracy_mm,
completeness_mm, fscore_5mm, normal_error_deg) and preview.png (the mesh, and the ground truth beside it).

Examples:
  spadscan baseline space-carving captures/bunny --out out/bunny-carve --gt bunny.obj
  spadscan baseline reprojection captures/bunny --out out/bunny-reproj --gt bunny.obj --calibrate
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from spadscan.protocol.errors import ConfigError
from spadscan.worker.ground_truth import add_ground_truth_options, ground_truth_for_run, load_ground_truth
from spadscan.worker.outputs import (check_ground_truth_kept, check_out, files_written_after, folder_files,
                                     replacing_result)

DEFAULTS = {"resolution": 128, "edge_deg": 1.0, "surface": "occupancy"}
"""Defaults of the options only one method reads (filled in after the check that the method reads them)."""

ONLY_FOR = {"space-carving": ("resolution", "margin_mm", "edge_deg"), "reprojection": ("surface",)}
"""The options each method alone reads: given to the other method, they are refused, not silently ignored."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("method", choices=("reprojection", "space-carving"), help="which baseline")
    parser.add_argument("capture", metavar="CAPTURE", help="capture folder (holds scan.json)")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="folder for the results: mesh.ply, report.json, report.html, view3d.html, preview.png "
                             "(and points.ply for reprojection)")
    add_ground_truth_options(parser, ": adds metrics to the report")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the result already in --out: the files its report.json lists that this run "
                             "does not write again are removed, other files left (without it, a folder that holds "
                             "mesh.ply or report.json is refused)")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--threshold", type=float, default=None, metavar="T",
                       help="detection threshold in noise standard deviations (default: the sensor's: 20 on a "
                            "TMF8820, 5 on others)")
    group.add_argument("--calibrate", action="store_true",
                       help="search the threshold for the best Chamfer against the ground truth (as the paper did)")
    parser.add_argument("--resolution", type=int, default=None, metavar="R",
                        help=f"space carving: voxels along each side of the grid (default: {DEFAULTS['resolution']})")
    parser.add_argument("--margin-mm", type=float, default=None, metavar="MM",
                        help="space carving: range left uncarved in front of each first return, mm "
                             "(default: one bin, at least 2 mm)")
    parser.add_argument("--edge-deg", type=float, default=None, metavar="DEG",
                        help="space carving: trust each zone's field of view only this far inside its edges "
                             f"(default: {DEFAULTS['edge_deg']:g} degree)")
    floor = parser.add_mutually_exclusive_group()
    floor.add_argument("--floor-z", type=float, default=None, metavar="M",
                       help="height of the floor the object stands on, metres; below it is empty (default: a "
                            "measured capture's table, found in its histograms as the fast reconstruction finds it; "
                            "z = 0 for a simulated one). Refused above every sensor position, or farther below them "
                            "than the histograms reach")
    floor.add_argument("--no-floor", action="store_true", help="do not assume a floor")
    parser.add_argument("--points", type=int, default=300_000, metavar="N",
                        help="sample points per mesh for the metrics against the ground truth (default: 300,000, "
                             "the project's convention; fewer are faster and coarser)")
    parser.add_argument("--surface", choices=("occupancy", "convex-hull"), default=None,
                        help=f"reprojection: how the points become a surface (default: {DEFAULTS['surface']})")


def check_method_options(args) -> None:
    """Refuse an option the chosen method does not read, then fill in the defaults of those it does."""
    for method, names in ONLY_FOR.items():
        given = [name for name in names if getattr(args, name) is not None]
        if method != args.method and given:
            flags = ", ".join("--" + name.replace("_", "-") for name in given)
            raise ConfigError(f"{flags}: only {method} reads {'it' if len(given) == 1 else 'them'}, not "
                              f"{args.method}")
    for name, value in DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, value)


def run(args) -> int:
    from spadscan.worker.baselines.run import run_baseline  # numpy, scipy and trimesh: only when a baseline runs
    from spadscan.worker.metrics import MAX_POINTS

    check_method_options(args)
    if not 8 <= args.resolution <= 512:
        raise ConfigError(f"--resolution {args.resolution} must lie in [8, 512]")
    if args.margin_mm is not None and not args.margin_mm >= 0:
        raise ConfigError(f"--margin-mm {args.margin_mm} must be >= 0")
    if args.floor_z is not None and not math.isfinite(args.floor_z):
        raise ConfigError(f"--floor-z {args.floor_z} must be a finite height in metres (or --no-floor)")
    if not math.isfinite(args.edge_deg):
        raise ConfigError(f"--edge-deg {args.edge_deg} must be a finite angle in degrees")
    if not 1 <= args.points <= MAX_POINTS:
        raise ConfigError(f"--points {args.points} must be an integer in [1, {MAX_POINTS:,}]")
    if args.threshold is not None and not args.threshold > 0:
        raise ConfigError(f"--threshold {args.threshold} must be > 0 (noise standard deviations)")

    out = check_out(args.out, args.overwrite, capture=args.capture)  # --out too: before the calibration's minutes

    def log(line: str) -> None:
        print(f"spadscan baseline: {line}", file=sys.stderr, flush=True)

    gt, gt_note = ground_truth_for_run(args.capture, args.gt, args.no_gt, log)
    if args.overwrite:
        check_ground_truth_kept(gt, out)
    started = time.monotonic()
    with replacing_result(args.out, log):  # a previous result stays whole until this run has finished
        before = folder_files(args.out)  # the user's own files there are no part of the result
        report = run_baseline(
            args.capture, args.out, args.method, gt=gt, threshold=args.threshold, calibrate_=args.calibrate,
            resolution=args.resolution, margin_m=None if args.margin_mm is None else args.margin_mm * 1e-3,
            floor_z=None if args.no_floor else ("auto" if args.floor_z is None else args.floor_z),
            surface=args.surface, edge_deg=args.edge_deg, metrics_points=args.points, log=log)
        if gt_note:
            report["ground_truth_note"] = gt_note  # the page says why it has no metrics
        log("drawing the pictures and writing report.html")
        write_pictures_and_page(report, args.out, gt, before)
    source = report.get("threshold_source", "")
    line = f"{args.method}: threshold {report['threshold']:g}" + (f" ({source})" if source != "given" else "")
    # The method's own time (report.json's seconds) apart from the run's: metrics on 300,000 points and the
    # pictures take most of it.
    line += f", {report['seconds']:.1f} s to build, {time.monotonic() - started:.1f} s in all"
    if "chamfer_mm" in report:
        line += (f", Chamfer {report['chamfer_mm']:.2f} mm (accuracy {report['accuracy_mm']:.2f}, completeness "
                 f"{report['completeness_mm']:.2f}), F-score@5mm {report['fscore_5mm']:.3f}")
    if report.get("implausible_hull"):
        line += " - IMPLAUSIBLE hull (see the warning)"
    print(f"{line} -> {args.out}")
    return 0


def write_pictures_and_page(report: dict, out, gt, before: dict[str, int]) -> None:
    """preview.png (mesh, and ground truth when given) and report.html beside the baseline's report.json, which
    then lists the files this run wrote (`files`)."""
    from spadscan.protocol.mesh_io import load_mesh  # trimesh and matplotlib: only when a baseline ran
    from spadscan.worker.report.folder_view import ensure_view3d
    from spadscan.worker.report.pictures import preview_or_warning
    from spadscan.worker.report.report_html import write_report_html
    from spadscan.worker.report.report_json import write_report

    out = Path(out)
    # The part of the ground truth that was scored (above its table, when it holds one), as reconstruct shows it:
    # a 2 m table slab beside the object would shrink the object to a speck.
    gt_mesh = load_ground_truth(gt).mesh if gt is not None else None
    missing = preview_or_warning(load_mesh(out / "mesh.ply"), out / "preview.png", gt=gt_mesh)
    if missing is not None:  # the report says why it has no preview, as reconstruct's does
        report["warnings"] = [*report.get("warnings", []), missing]
    ensure_view3d(report, out)  # before the files are listed: a view that cannot be made leaves no stale one
    written = files_written_after(out, before) | {"report.json", "report.html"}
    report["files"] = sorted(written)
    write_report(out, report)
    write_report_html(report, out)
