"""Compare a mesh with ground truth: Chamfer, accuracy, completeness (mm), F-score at 5 mm, normal error (degrees).

Both meshes are sampled uniformly by area (--points each, fixed --seed) and compared point to point (docs/metrics.md):
accuracy = mean distance MESH -> GT, completeness = mean GT -> MESH, Chamfer = (accuracy + completeness) / 2.
Identical meshes score about 0.5 sqrt(area / points) (~0.35 mm for the bunny at 300,000 points), the floor of this
estimate. Meshes are read in metres; STL (and OBJ/PLY/OFF) files larger than 5 m are taken to be in millimetres.
Either mesh may be `builtin:NAME`, a built-in scene.

A ground truth that includes the table the object stands on (a slab: one upward-facing level holding over a quarter
of its area, like LCSPCData's pyramid2.stl) is scored on the object: both meshes are cut 5 mm above the table top,
as the worker's reports and the benchmark do (--keep-table scores everything). --box crops both meshes to an
axis-aligned box instead.

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
                        help="points sampled on each mesh (default: 300000)")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="sampling seed (default: 0)")
    parser.add_argument("--threshold-mm", type=float, default=5.0, metavar="T",
                        help="F-score distance threshold in mm (default: 5)")
    parser.add_argument("--units", default="auto", choices=("auto", "m", "mm"),
                        help="units of both mesh files (default: auto, millimetres detected by size)")
    parser.add_argument("--box", type=float, nargs=6, default=None, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                        help="crop both meshes to this box (metres) before comparing (instead of the cut above a "
                             "table)")
    parser.add_argument("--keep-table", action="store_true",
                        help="score a ground truth's table too (default: the object above it)")


def format_table(metrics, mesh: str, gt: str, scored: str | None = None) -> str:
    """The metrics as a small aligned table (mm and degrees); `scored`: what part of the meshes was compared."""
    m = metrics
    rows = [
        ("reconstruction", mesh),
        ("ground truth", gt),
        *([("scored", scored)] if scored else []),
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

    from spadscan.protocol.errors import ConfigError

    from spadscan.protocol.mesh_io import MM_EXTENT_THRESHOLD_M, load_mesh_spec
    from spadscan.worker.ground_truth import GroundTruth, load_ground_truth
    from spadscan.worker.metrics import crop_to_box

    if not (math.isfinite(args.threshold_mm) and 0 < args.threshold_mm < 10_000):
        raise ConfigError(f"--threshold-mm {args.threshold_mm:g} must be a distance in (0, 10000) mm")
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
    metrics = truth.metrics(pred, n_points=args.points, seed=args.seed, fscore_threshold_m=args.threshold_mm * 1e-3)
    if args.json:
        # ground_truth and ground_truth_cut_above_z_m: the keys reconstruct's and baseline's reports use.
        print(json.dumps({"mesh": args.mesh, "gt": args.gt, "ground_truth": args.gt, "mesh_units": units["mesh"],
                          "gt_units": units["gt"], "cut_above_z_m": truth.cut_above_z_m,
                          "ground_truth_cut_above_z_m": truth.cut_above_z_m,
                          **metrics.to_dict()}))
    else:
        print(format_table(metrics, args.mesh, args.gt, truth.note()))
    return 0
