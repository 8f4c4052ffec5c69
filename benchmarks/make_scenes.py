"""Simulated captures of the built-in validation, holdout, check and tuning splits (the large tuning scenes a group of
their own) and of the tall objects on a table.

    python benchmarks/make_scenes.py --out FOLDER [--groups validation,holdout,check,tuning,large,aimed,table]
                                     [--seed 0] [--overwrite]

Writes one capture folder per scene into FOLDER, each through `spadscan simulate` with a fixed command line (printed
as it goes), so the same seed gives the same captures on any machine:

- validation, holdout, check: those splits (protocol/scenes.py SPLITS) in the public dataset's simulated format: sensor
  lcspc-sim, 256 views on the Fibonacci spiral at 0.5 m looking at the origin, no table.
- tuning: the tuning split's built-ins but the large ones, in the same format (the dataset's own three scenes are
  imported from it: `spadscan import-lcspc`).
- large: the tuning split's four 0.35 m scenes (LARGE_SCENES), in the same format: their tops 0.15 m from the views
  above them.
- aimed: the validation split's scenes with the same views aimed at each object's mid-height, as a rig is often set
  up (named NAME-mid): the views cover it otherwise than the dataset's, which aim at the floor under it. Never tuned
  on either.
- table: the tall objects (TABLE_SCENES) on a black table, as a real capture sees them: sensor tmf8820, 120 views
  on 8 elevation rings from 36 to 83 degrees (the real captures' layout), looking at the object's mid-height from
  0.45 m (head on a can) or 0.40 m (tall block), so that the sensor stays 0.2-0.6 m from the surface.

Then run, e.g.:

    python benchmarks/error_vs_time.py --scenes FOLDER/* --budget-s 180 --out benchmark-out/validation
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from spadscan.cli import main as spadscan
from spadscan.protocol.folders import folder_problem
from spadscan.protocol.scenes import SPLITS, TABLE_SCENES, builtin_scene

VALIDATION_OPTIONS = ["--sensor", "lcspc-sim", "--views", "256"]
"""LCSPCData's simulated scenes: the spiral's defaults (0.5 m, elevations up to 86 degrees) with its sensor."""

TABLE_OPTIONS = ["--sensor", "tmf8820", "--table", "--views", "120", "--schedule", "rings", "--rings", "8",
                 "--min-elevation", "36", "--max-elevation", "83"]
"""The real captures' layout (8 elevation rings from 36 to 83 degrees, 15-16 azimuths each) with the real sensor."""

TABLE_RADIUS_M = {"head-on-can": 0.45, "tall-block": 0.40}
"""Distance from the sensor to the object's mid-height: the sensor 0.2-0.6 m from the surface."""

LARGE_SCENES = ("big-lamp", "big-cup", "big-goblet", "tall-egg")
"""The tuning split's built-ins made 0.35 m tall (protocol/scenes.py)."""

GROUPS = ("validation", "holdout", "check", "tuning", "large", "aimed", "table")


def plans(groups, seed: int) -> list[tuple[str, list[str]]]:
    """(capture folder name, `spadscan simulate` arguments without --out) for every scene of the groups."""
    out = []
    for split in ("validation", "holdout", "check"):
        if split in groups:
            for spec in SPLITS[split]:
                name = spec.split(":", 1)[1]
                out.append((name, [spec, *VALIDATION_OPTIONS, "--seed", str(seed)]))
    if "tuning" in groups:
        names = [s.split(":", 1)[1] for s in SPLITS["tuning"] if s.startswith("builtin:")]
        out += [(name, [f"builtin:{name}", *VALIDATION_OPTIONS, "--seed", str(seed)])
                for name in names if name not in LARGE_SCENES]
    if "large" in groups:
        out += [(name, [f"builtin:{name}", *VALIDATION_OPTIONS, "--seed", str(seed)]) for name in LARGE_SCENES]
    if "aimed" in groups:
        for spec in SPLITS["validation"]:
            name = spec.split(":", 1)[1]
            out.append((f"{name}-mid", [spec, *VALIDATION_OPTIONS, "--target", "0", "0", str(_mid_height(name)),
                                        "--seed", str(seed)]))
    if "table" in groups:
        for name in TABLE_SCENES:
            mid = _mid_height(name)
            out.append((f"{name}-table", [f"builtin:{name}", *TABLE_OPTIONS, "--radius", str(TABLE_RADIUS_M[name]),
                                          "--target", "0", "0", str(mid), "--seed", str(seed)]))
    return out


def _mid_height(name: str) -> float:
    """Half the height (metres, 1 mm steps) of a built-in scene, which stands on z = 0."""
    return round(float(builtin_scene(name).bounds[1, 2]) / 2, 3)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, type=Path, help="folder to write one capture folder per scene into")
    parser.add_argument("--groups", default=",".join(GROUPS),
                        help=f"comma-separated groups of scenes (default: {','.join(GROUPS)})")
    parser.add_argument("--seed", type=int, default=0, help="simulation seed of every capture (default: 0)")
    parser.add_argument("--overwrite", action="store_true", help="replace captures of the same names in --out")
    args = parser.parse_args(argv)
    groups = [g for g in args.groups.split(",") if g]
    unknown = sorted(set(groups) - set(GROUPS))
    if unknown or not groups:
        parser.error(f"--groups {args.groups!r}: choose from {', '.join(GROUPS)}")
    if args.seed < 0:
        parser.error(f"--seed {args.seed} must be >= 0")
    if args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out}: exists and is not a folder")
    if (unmakeable := folder_problem(args.out)) is not None:
        parser.error(f"--out {args.out}: {unmakeable}")
    todo = plans(groups, args.seed)
    existing = [name for name, _ in todo if (args.out / name).exists()]
    if existing and not args.overwrite:
        parser.error(f"{args.out} already holds {', '.join(existing)} (add --overwrite to replace them)")
    args.out.mkdir(parents=True, exist_ok=True)
    for name, sim_args in todo:
        target = args.out / name
        if target.exists():
            shutil.rmtree(target)
        command = ["simulate", *sim_args, "--out", str(target), "--no-progress"]
        print("spadscan " + " ".join(command), flush=True)
        start = time.monotonic()
        if spadscan(command) != 0:
            print(f"make_scenes: {name} failed (see above)", file=sys.stderr)
            return 1
        print(f"  {name}: {time.monotonic() - start:.1f} s", flush=True)
    print(f"{len(todo)} captures in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
