"""Compare a mesh with ground truth: Chamfer, accuracy, completeness (mm), F-score at 5 mm, normal error (degrees).

Both meshes are sampled uniformly by area (--points each, fixed --seed) and compared point to point (docs/metrics.md):
accuracy = mean distance MESH -> GT, completeness = mean GT -> MESH, Chamfer = (accuracy + completeness) / 2.
Identical meshes score about 0.5 sqrt(area / points) (~0.35 mm for the bunny at 300,000 points), the floor of this
estimate; fewer than 1000 --points are refused, since their floor reaches the F-score's 5 mm. Meshes are read in
metres; STL (and OBJ/PLY/OFF) files larger than 5 m are taken to be in millimetres, and a mesh still over 10 km
across is refused (a units or export error: nothing scanned is that large). Either mesh may be `builtin:NAME`, a
built-in scene.

A ground truth that includes the table the object stands on (a slab: one upward-facing level holding over a quarter
of its area, like LCSPCData's pyramid2.stl) is scored on the object: both meshes are cut 5 mm above the table top,
as the worker's reports and the benchmark do (--keep-table scores everything). --box crops both meshes to an
axis-aligned box instead (what of the table lies inside the box is scored with the object); the table and the JSON
(`box_m`) name the box.

A note (the table's `note` line, `mismatch_note` in the JSON) says when the two meshes plainly are not the same object
in the same units and frame: their bounding boxes do not overlap, or differ over 5x in size (a mesh in cm read as
metres is 100x too large; not judged with --keep-table or --box, where a table may be scored). The score is printed
all the same.

The distances are measured within --budget-s seconds (120 by default; meshes of a scanned object's size take seconds):
a reconstruction lying inside a much larger ground truth can make the exact nearest samples slow to find, and once the
budget is spent the figures rest on the samples measured so far, a coarser estimate that the table's `measured` line
(`measured_note` in the JSON, and `queries`) says.

Examples:
  spadscan eval recon.obj --gt bunny.obj
  spadscan eval recon.obj --gt builtin:demo --json
  spadscan eval recon.ply --gt pyramid2.stl        # the pyramid above its table
  spadscan eval recon.stl --gt pyramid2.stl --box -0.2 -0.75 -0.15 0.2 -0.35 0.1
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mesh", metavar="MESH", help="the reconstruction: a mesh file (metres) or builtin:NAME")
    parser.add_argument("--gt", required=True, metavar="GT", help="the ground truth: a mesh file or builtin:NAME")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    parser.add_argument("--points", type=int, default=300_000, metavar="N",
                        help=f"points sampled on each mesh, {MIN_POINTS} to 20000000 (default: 300000; fewer than "
                             f"{MIN_POINTS} measure the sampling, not the meshes)")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="sampling seed (default: 0)")
    parser.add_argument("--threshold-mm", type=float, default=5.0, metavar="T",
                        help="F-score distance threshold in mm (default: 5)")
    parser.add_argument("--units", default="auto", choices=("auto", "m", "mm"),
                        help="units of both mesh files (default: auto, millimetres detected by size)")
    parser.add_argument("--box", type=float, nargs=6, default=None, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                        help="crop both meshes to this box (metres) before comparing, instead of the cut above a "
                             "table: what of a table lies inside the box is scored (so not with --keep-table)")
    parser.add_argument("--budget-s", type=float, default=BUDGET_S, metavar="S",
                        help=f"seconds for measuring the distances (default: {BUDGET_S:g}); past them the figures "
                             "rest on the samples measured so far, and say so")
    parser.add_argument("--keep-table", action="store_true",
                        help="score a ground truth's table too (default: the object above it; not with --box)")


MIN_POINTS = 1000
"""The fewest samples per mesh eval takes: two samplings of one surface lie about 0.5 sqrt(area / points) apart, 5 mm
for a 20 cm object at 1000 points, as much as the F-score's threshold; fewer score the sampling, not the meshes."""
BUDGET_S = 120.0
"""Seconds eval measures distances for by default: the bunny at 300,000 points takes a few, a ground truth many times
the reconstruction around it took minutes."""
WHO = {"mesh": "the reconstruction", "gt": "the ground truth"}


def units_line(units: dict, option: str) -> str | None:
    """What the table says of the units when a mesh was read as millimetres (None: both in metres, the default);
    `units`: {"mesh": "m"|"mm", "gt": ...}, `option`: --units."""
    from spadscan.protocol.mesh_io import MM_EXTENT_THRESHOLD_M

    read_mm = [what for what, unit in units.items() if unit == "mm"]
    if not read_mm:
        return None
    which = "both" if len(read_mm) == 2 else WHO[read_mm[0]]
    why = "--units mm" if option == "mm" else f"over {MM_EXTENT_THRESHOLD_M:g} m across as metres"
    return f"{which} read as millimetres ({why})"


def box_line(box) -> str:
    """The table's `scored` line for --box (six numbers, metres)."""
    corners = [", ".join(f"{v:g}" for v in corner) for corner in (box[:3], box[3:])]
    return f"both meshes inside the box [{corners[0]}] .. [{corners[1]}] m (--box)"


def mismatch_note(mesh, gt, compare_sizes: bool = True) -> str | None:
    """`metrics.mismatch` of the scored meshes, with what to check, or None. Sizes are not compared where a table was
    kept (--keep-table, --box): a ground truth's table slab is many times its object, which no reconstruction holds."""
    from spadscan.worker.metrics import mismatch

    found = mismatch(mesh, gt, compare_sizes)
    return None if found is None else f"{found}: check that both are in the same units (--units m|mm) and frame"


def measured_note(metrics, budget_s: float) -> str | None:
    """One line when the budget cut the distances short (`metrics.queries` below `n_points`), else None."""
    if metrics.queries >= metrics.n_points:
        return None
    return (f"{metrics.queries:,} of the {metrics.n_points:,} samples per mesh within --budget-s {budget_s:g}: a "
            f"coarser estimate (a larger --budget-s measures more)")


def format_table(metrics, mesh: str, gt: str, scored: str | None = None, units: str | None = None,
                 note: str | None = None, measured: str | None = None) -> str:
    """The metrics as a small aligned table (mm and degrees); `scored`: what part of the meshes was compared,
    `units`: how they were read (`units_line`), `note`: `mismatch_note`, `measured`: `measured_note` (each left
    out when None)."""
    m = metrics
    said = (("units", units), ("scored", scored), ("note", note), ("measured", measured))
    rows = [
        ("reconstruction", mesh),
        ("ground truth", gt),
        *[(name, value) for name, value in said if value],
        ("Chamfer", f"{m.chamfer_mm:8.3f} mm"),
        ("accuracy", f"{m.accuracy_mm:8.3f} mm   (reconstruction -> ground truth)"),
        ("completeness", f"{m.completeness_mm:8.3f} mm   (ground truth -> reconstruction)"),
        (f"F-score @{m.fscore_threshold_mm:g} mm", f"{m.fscore_5mm:8.4f}      (precision {m.precision:.4f}, "
                                                  f"recall {m.recall:.4f})"),
        ("normal error", f"{m.normal_error_deg:8.2f} deg"),
        ("samples", f"{m.n_points} per mesh, seed {m.seed}"),
    ]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def run(args: argparse.Namespace) -> int:
    import json
    import math
    import sys
    import time

    from spadscan.protocol.errors import ConfigError

    from spadscan.protocol.mesh_io import MM_EXTENT_THRESHOLD_M, load_mesh_spec
    from spadscan.worker.ground_truth import GroundTruth, load_ground_truth
    from spadscan.worker.metrics import MAX_POINTS, crop_to_box, mesh_metrics

    if not MIN_POINTS <= args.points <= MAX_POINTS:
        raise ConfigError(f"--points {args.points} must be in [{MIN_POINTS}, {MAX_POINTS}] (samples per mesh; fewer "
                          f"than {MIN_POINTS} score the sampling, not the meshes)")
    if not (math.isfinite(args.budget_s) and args.budget_s > 0):
        raise ConfigError(f"--budget-s {args.budget_s:g} must be a finite number of seconds > 0")
    if not (math.isfinite(args.threshold_mm) and 0 < args.threshold_mm < 10_000):
        raise ConfigError(f"--threshold-mm {args.threshold_mm:g} must be a distance in (0, 10000) mm")
    if args.box is not None and args.keep_table:
        # The box replaces the cut: a table inside it is scored anyway, so --keep-table would change nothing.
        raise ConfigError("--keep-table and --box: the box replaces the cut above a table (what of the table lies "
                          "inside the box is scored); give --box alone")
    pred = load_mesh_spec(args.mesh, units=args.units)[0]
    truth = load_ground_truth(args.gt, units=args.units, keep_table=args.keep_table or args.box is not None)
    units = {"mesh": pred.metadata.get("units_read", "m"), "gt": truth.units_read}
    for what, unit in units.items():
        if unit == "mm" and args.units == "auto":  # said, since a silent x1000 is a surprise
            print(f"{getattr(args, what)}: read as millimetres (over {MM_EXTENT_THRESHOLD_M:g} m across as metres; "
                  f"--units m to read it as metres)", file=sys.stderr)
    if args.box is not None:
        pred = crop_to_box(pred, args.box[:3], args.box[3:], what=f"the mesh {args.mesh}")
        truth = GroundTruth(crop_to_box(truth.mesh, args.box[:3], args.box[3:], what=f"the ground truth {args.gt}"))
    scored = truth.scored(pred)  # what GroundTruth.metrics compares, kept to check the two meshes against each other
    note = mismatch_note(scored, truth.mesh, compare_sizes=not args.keep_table and args.box is None)
    metrics = mesh_metrics(scored, truth.mesh, n_points=args.points, seed=args.seed,
                           fscore_threshold_m=args.threshold_mm * 1e-3, deadline=time.perf_counter() + args.budget_s)
    measured = measured_note(metrics, args.budget_s)
    box = None if args.box is None else [list(args.box[:3]), list(args.box[3:])]
    if args.json:
        # ground_truth and ground_truth_cut_above_z_m: the keys reconstruct's and baseline's reports use.
        print(json.dumps({"mesh": args.mesh, "gt": args.gt, "ground_truth": args.gt, "mesh_units": units["mesh"],
                          "gt_units": units["gt"], "cut_above_z_m": truth.cut_above_z_m,
                          "ground_truth_cut_above_z_m": truth.cut_above_z_m, "box_m": box,
                          "mismatch_note": note, "measured_note": measured, **metrics.to_dict()}))
    else:
        scored_line = box_line(args.box) if args.box is not None else truth.note()
        print(format_table(metrics, args.mesh, args.gt, scored_line, units_line(units, args.units), note,
                           measured))
    return 0
