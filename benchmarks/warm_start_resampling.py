"""Does a live job's refitting blur its surface? A field carried through repeated warm starts onto shifted grids,
against the same field carried through none.

    python benchmarks/warm_start_resampling.py CAPTURE [--steps 1500] [--rebuilds 13] [--seed 0]

A live job rebuilds its model as views arrive, and each new model's grid follows the new hull's box: its origin
moves and its voxel changes a little, and `FastModel.warm_start` samples the old field (trilinearly) at the new grid's
nodes. Repeated, such resampling smooths a surface. This fits CAPTURE offline (`fast`, one thread, --steps, seeded),
then carries its field through --rebuilds resamplings onto grids shifted by up to one voxel on each axis (and, in the
second row, with voxels up to 3 % larger or smaller), and prints the Chamfer distance (mm, 300,000 points, against
the capture's ground truth) after 1, 4 and all of them, beside the field warm-started once onto its own grid.
Step-based and seeded: the figures do not depend on the machine.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from error_vs_time import chamfer_mm, ground_truth  # noqa: E402

from spadscan.protocol.errors import SpadscanError  # noqa: E402
from spadscan.worker.recon.model_api import RunPlan  # noqa: E402
from spadscan.worker.recon.trainer import train  # noqa: E402
from spadscan.worker.reconstruct import resolve_device, run_config, set_up_run  # noqa: E402

SCORE_POINTS = 300_000
MESH_CELLS = 256


def resampled(field, rng: np.random.Generator, scale: float):
    """`field` sampled at the nodes of a grid of the same shape, shifted by up to a voxel on each axis and with a
    voxel up to `scale` (relative) larger or smaller."""
    origin = field.origin.detach().cpu().numpy() + rng.uniform(-1.0, 1.0, 3) * field.voxel
    voxel = field.voxel * (1.0 + rng.uniform(-scale, scale))
    shape = field.sdf.shape[-3:]
    probe = type(field)(origin, voxel, torch.zeros(shape, dtype=field.sdf.dtype))
    values = field.sample(probe.node_points().to(field.origin.dtype)).to(field.sdf.dtype)
    return type(field)(origin, voxel, values.reshape(shape))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture", type=Path, help="a capture folder that names its ground truth")
    ap.add_argument("--steps", type=int, default=1500, help="steps of the fit, >= 1 (default 1500)")
    ap.add_argument("--rebuilds", type=int, default=13, help="resamplings the field is carried through, >= 1 "
                                                              "(default 13)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the fit and the grid shifts, >= 0 (default 0)")
    args = ap.parse_args(argv)
    # Every column is a count of resamplings from 1 to --rebuilds: with none, the table would announce columns it
    # has no figures for.
    if args.steps < 1 or args.rebuilds < 1 or args.seed < 0:
        ap.error("--steps and --rebuilds must be >= 1 and --seed >= 0")
    if not (args.capture / "scan.json").is_file():
        print(f"warm_start_resampling: {args.capture} is not a capture folder (no scan.json)", file=sys.stderr)
        return 2
    try:
        return measure(args)
    except SpadscanError as exc:  # a capture that does not load or fit: one line, not a traceback
        print(f"warm_start_resampling: error: {exc}", file=sys.stderr)
        return 1


def measure(args) -> int:
    """Fit the capture, carry its field through the resamplings and print the table."""
    torch.set_num_threads(1)
    config = run_config("fast", {})
    truth = ground_truth(args.capture)
    if truth is None:
        print(f"warm_start_resampling: {args.capture} names no ground truth", file=sys.stderr)
        return 2
    model = set_up_run(args.capture, config, resolve_device("cpu"), steps=args.steps, budget_s=None,
                       seed=args.seed, log=lambda line: None).model
    train(model, RunPlan(steps=args.steps, budget_s=None, seed=args.seed), every_s=1e9, evaluate=None,
          progress=False, early_stop=config.early_stop)
    f0 = model.mesh_field()
    base = type(f0)(f0.origin.detach().cpu().numpy(), f0.voxel, f0.sdf.detach()[0, 0].clone())

    def score(field) -> float:
        model.warm_start(field, model.level, model.level_steps)
        return chamfer_mm(model.extract_mesh(MESH_CELLS), truth, SCORE_POINTS)

    marks = sorted({1, min(4, args.rebuilds), args.rebuilds})
    print(f"{args.capture.name}: fast, {args.steps} steps, seed {args.seed}; Chamfer mm after n resamplings")
    print("| grids | n = 0 | " + " | ".join(f"n = {n}" for n in marks) + " |")
    print("|---|---|" + "---|" * len(marks))
    for name, scale in (("shifted", 0.0), ("shifted, voxel +-3 %", 0.03)):
        rng = np.random.default_rng(args.seed)
        field, row = base, [score(base)]
        for n in range(1, args.rebuilds + 1):
            field = resampled(field, rng, scale)
            if n in marks:
                row.append(score(field))
        print(f"| {name} | " + " | ".join(f"{v:.3f}" for v in row) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
