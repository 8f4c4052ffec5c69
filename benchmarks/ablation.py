"""What each part of the `fast` preset buys: every scene fitted with all parts, then with each part switched off alone.

    python benchmarks/ablation.py --scenes DIR... --out FOLDER [--steps 3000] [--seed 0] [--threads 1]
                                  [--parts NAME,...] [--points 300000] [--set KEY=VALUE ...]
                                  [--device cpu|cuda] [--jobs N] [--overwrite]

A scene is a capture folder or a folder of the public dataset (imported once into --out, as
benchmarks/error_vs_time.py does). For each scene the default run comes first; its report says which parts ran on
that scene (a part that does not apply, say the table on a scene without one, is not ablated there). Then one run per
part with `--set parts.NAME.enabled=false`, except the average and the plateau test, which change nothing in the
fit: the default run also meshes its last grid (average off) and goes on to --steps after its early stop (plateau
off). Runs are step-based and seeded (at most --steps steps, the early stop as
configured, one thread by default), so the figures do not depend on the machine's load; each runs in its own process
and is scored like `spadscan reconstruct`'s final mesh (300,000 points, the full mesh resolution). `--jobs N` runs N
at once (every scene's all-parts run first, then the ablations); `--device cuda` fits on the GPU (seeded, but CUDA's
sums are not bit-for-bit repeatable: figures there vary a little from run to run).

Writes runs/<scene>--<variant>.json as each run ends, with the settings it ran with (--steps, --seed, --threads,
--points, --device and its --set overrides). A later call with the same --out reuses the runs made with its own
settings, so an interrupted ablation resumes where it stopped (Ctrl-C writes the table of the runs finished); an
--out holding a run made with other settings is refused, in one line that says which (--overwrite starts afresh).
Then table.md: per part and scene, the Chamfer (mm) and the mean normal error (degrees) with the part off, against
all parts on, and the steps each run took.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from error_vs_time import ground_truth, prepare_scene, scene_problem, source_commit, write_atomic  # noqa: E402

ALL = "all parts"


DERIVED = ("average", "plateau")
"""Parts whose ablation the all-parts run gives without a run of its own: neither changes the fit. Without the
average the mesh comes from the grid as it is (the same fit, meshed from its last step); without the plateau test
the run goes on to --steps (the same fit up to the early stop, continued)."""


SETTINGS = {"steps": "--steps", "seed": "--seed", "threads": "--threads", "points": "--points", "device": "--device",
            "overrides": "--set"}
"""What a run's figures depend on besides its scene and the code, and the option that sets each."""


def settings_of(steps: int, seed: int, threads: int, points: int, device: str, overrides: list[str]) -> dict:
    """A run's settings (SETTINGS) as its file records them."""
    return {"steps": steps, "seed": seed, "threads": threads, "points": points, "device": device,
            "overrides": list(overrides)}


def variant_overrides(overrides: list[str], variant: str) -> list[str]:
    """The --set overrides of a variant's run: the call's, and the part switched off."""
    return list(overrides) + ([] if variant == ALL else [f"parts.{variant}.enabled=false"])


def other_settings(recorded: dict | None, wanted: dict) -> str | None:
    """How a run file's recorded settings differ from `wanted` ('--steps 5, not 40'), or None when they do not."""
    if not isinstance(recorded, dict):
        return "no settings recorded (made before they were)"

    def shown(key, value):
        return (" ".join(value) or "none") if key == "overrides" and isinstance(value, list) else value

    diffs = [f"{flag} {shown(key, recorded.get(key))}, not {shown(key, wanted[key])}"
             for key, flag in SETTINGS.items() if recorded.get(key) != wanted[key]]
    return "; ".join(diffs) or None


def run_one(capture: Path, steps: int, seed: int, threads: int, overrides: list[str], points: int = 300_000,
            device: str = "cpu") -> dict:
    """One step-based run of the fast preset on `capture`, scored against its ground truth. A run with every part
    that runs also scores the `DERIVED` ablations (`derived`: part -> the same fields)."""
    import torch

    from spadscan.worker.recon.config import parse_override
    from spadscan.worker.recon.model_api import RunPlan
    from spadscan.worker.recon.trainer import train
    from spadscan.worker.reconstruct import run_config, set_up_run

    torch.set_num_threads(threads)
    config = run_config("fast", dict(parse_override(text) for text in overrides))
    truth = ground_truth(capture)
    run = set_up_run(capture, config, torch.device(device), steps=steps, budget_s=None, seed=seed,
                     log=lambda line: None)
    model = run.model
    result = train(model, run.plan, progress=False, early_stop=config.early_stop)

    def scored(record: dict, averaged: bool = True) -> dict:
        if truth is not None:
            m = truth.metrics(model.extract_mesh(config.mesh_resolution, averaged=averaged),
                              n_points=points, seed=seed)
            record.update(chamfer_mm=m.chamfer_mm, accuracy_mm=m.accuracy_mm, completeness_mm=m.completeness_mm,
                          normal_error_deg=m.normal_error_deg, fscore_5mm=m.fscore_5mm)
        return record

    out = scored({"steps": result.steps, "stopped_by": result.stopped_by, "train_s": result.seconds,
                  "setup_s": run.setup_s, "overrides": overrides, "summary": model.summary(),
                  "commit": source_commit(), "config": config.to_dict(), "threads": threads, "device": device,
                  "settings": settings_of(steps, seed, threads, points, device, overrides)})
    ran = set(model.summary()["parts"])
    if not any(o.startswith("parts.") and o.endswith(".enabled=false") for o in overrides):
        derived = {}
        if "average" in ran:
            derived["average"] = scored({"steps": result.steps, "stopped_by": result.stopped_by}, averaged=False)
        if "plateau" in ran:
            more = steps - result.steps if result.stopped_by == "converged" else 0
            extra = train(model, RunPlan(steps=more, budget_s=None, seed=seed), progress=False) if more else None
            derived["plateau"] = scored({"steps": steps if more else result.steps,
                                         "stopped_by": extra.stopped_by if extra else result.stopped_by})
        out["derived"] = derived
    return out


def run_in_child(capture: Path, target: Path, args, overrides: list[str]) -> dict | None:
    """Run `run_one` in a fresh process (clean memory, nothing shared); its result, or None when it failed."""
    cmd = [sys.executable, __file__, "--one", str(capture), "--result", str(target), "--steps", str(args.steps),
           "--seed", str(args.seed), "--threads", str(args.threads), "--points", str(args.points),
           "--device", args.device]
    cmd += [f"--set={o}" for o in overrides]
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()
        print(f"  failed: {tail[-1] if tail else 'exit status ' + str(proc.returncode)}", flush=True)
        return None
    return json.loads(target.read_text())


def parts_that_ran(result: dict) -> list[str]:
    return list(result["summary"].get("parts", {}))


def fmt(v, digits=2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def cell(res: dict | None, base: dict | None, key: str, digits: int) -> str:
    """'value (+delta)' of a run against the all-parts run; '-' where it did not run."""
    if res is None or res.get(key) is None:
        return "-"
    if base is None or base is res or base.get(key) is None:
        return fmt(res[key], digits)
    return f"{fmt(res[key], digits)} ({res[key] - base[key]:+.{digits}f})"


def tables(results: dict[str, dict[str, dict]], variants: list[str]) -> str:
    scenes = list(results)
    lines = []
    for title, key, digits in (("Chamfer (mm), part off (change against all parts on)", "chamfer_mm", 2),
                               ("Mean normal error (degrees), part off (change)", "normal_error_deg", 1),
                               ("Steps (early stop)", "steps", 0)):
        lines += [f"### {title}", "", "| part off | " + " | ".join(scenes) + " |",
                  "|---|" + "---|" * len(scenes)]
        for v in variants:
            row = []
            for s in scenes:
                res = results[s].get(v)
                row.append("n/a" if res is None and v != ALL and v not in results[s].get("_ran", []) else
                           cell(res, results[s].get(ALL), key, digits))
            lines.append(f"| {v} | " + " | ".join(row) + " |")
        lines.append("")
    lines.append("n/a: the part does not run on that scene (see the all-parts run's report, `model.parts_left_out`).")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", type=Path, help="capture folders or dataset folders")
    parser.add_argument("--out", type=Path, help="folder for runs/, table.md and results.json")
    parser.add_argument("--steps", type=int, default=3000, help="at most this many steps a run (default: 3000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of every run (default: 0)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of every run (default: 1)")
    parser.add_argument("--points", type=int, default=300_000,
                        help="points sampled per mesh for the Chamfer (default: 300,000, as reconstruct scores)")
    parser.add_argument("--parts", default="", help="comma-separated parts to ablate (default: every part that runs)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                        help="override of every run, all parts included (repeatable)")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="where the fits run (default: cpu)")
    parser.add_argument("--jobs", type=int, default=1, help="runs at once (default: 1)")
    parser.add_argument("--overwrite", action="store_true", help="discard earlier runs in --out")
    parser.add_argument("--one", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one is not None:
        write_atomic(args.result, run_one(args.one, args.steps, args.seed, args.threads, args.overrides, args.points,
                                          args.device))
        return 0
    if not args.scenes or args.out is None:
        parser.error("--scenes and --out are required")
    if args.steps < 1 or args.threads < 1 or args.jobs < 1 or args.seed < 0 or not 1000 <= args.points <= 1_000_000:
        parser.error("--steps, --threads and --jobs must be >= 1, --seed >= 0 and --points in [1000, 1000000]")
    from spadscan.worker.recon.config import parse_override
    from spadscan.worker.recon.fast.parts import PARTS
    from spadscan.worker.reconstruct import run_config
    from spadscan.protocol.errors import SpadscanError

    names = [cls.name for cls in PARTS]
    wanted = [p for p in args.parts.split(",") if p] or names
    unknown = sorted(set(wanted) - set(names))
    if unknown:
        parser.error(f"--parts: no part {', '.join(unknown)} (parts: {', '.join(names)})")
    try:
        run_config("fast", dict(parse_override(text) for text in args.overrides))
    except SpadscanError as exc:
        parser.error(str(exc))
    for scene in args.scenes:
        why = scene_problem(scene)
        if why:
            parser.error(why)
    runs = args.out / "runs"
    if args.overwrite and runs.exists():
        for f in runs.glob("*.json"):
            f.unlink()

    def target_of(name: str, variant: str) -> Path:
        return runs / f"{name}--{variant.replace(' ', '-')}.json"

    def wanted_settings(variant: str) -> dict:
        return settings_of(args.steps, args.seed, args.threads, args.points, args.device,
                           variant_overrides(args.overrides, variant))

    # A run is reused only if it was made with this call's settings: any other would stand in the table under this
    # command line. Checked for every run this call could reuse, before any runs.
    for name in dict.fromkeys(scene.name for scene in args.scenes):
        for variant in [ALL] + [v for v in wanted if v not in DERIVED]:
            target = target_of(name, variant)
            if target.exists():
                try:
                    recorded = json.loads(target.read_text()).get("settings")
                except (OSError, ValueError, AttributeError):
                    recorded = None
                why = other_settings(recorded, wanted_settings(variant))
                if why:
                    parser.error(f"--out {args.out} holds a run made with other settings ({target.name}: {why}): "
                                 f"pass --overwrite to discard the earlier runs, or choose another --out")
    runs.mkdir(parents=True, exist_ok=True)
    captures = {scene.name: prepare_scene(scene, args.out) for scene in args.scenes}
    results: dict[str, dict[str, dict]] = {name: {} for name in captures}

    def record(name: str, variant: str, res: dict) -> None:
        results[name][variant] = res
        if variant == ALL:  # its report says which parts ran there, so which to ablate; and it gives DERIVED's
            results[name]["_ran"] = parts_that_ran(res)
            results[name].update({part: {**res, **d} for part, d in res.get("derived", {}).items() if part in wanted})

    def run(name: str, variant: str) -> None:
        # Recorded as it ends, in its own thread: an interrupt keeps every run that finished in the table.
        target = target_of(name, variant)
        if target.exists():
            record(name, variant, json.loads(target.read_text()))
            return
        t0 = time.perf_counter()
        print(f"{name}: {variant} ...", flush=True)
        res = run_in_child(captures[name], target, args, variant_overrides(args.overrides, variant))
        if res is not None:
            print(f"  {name}, {variant}: {fmt(res.get('chamfer_mm'))} mm, {fmt(res.get('normal_error_deg'), 1)} deg, "
                  f"{res['steps']} steps ({time.perf_counter() - t0:.0f} s)", flush=True)
            record(name, variant, res)

    interrupted = False
    try:
        with ThreadPoolExecutor(args.jobs) as pool:
            # Every scene's all-parts run first: its report says which parts ran there, so which to ablate.
            list(pool.map(lambda n: run(n, ALL), list(captures)))
            # Part by part across the scenes: an interrupted ablation leaves whole rows of the table.
            todo = [(name, v) for v in wanted for name in captures
                    if v in results[name].get("_ran", []) and v not in results[name]]
            list(pool.map(lambda nv: run(*nv), todo))
    except KeyboardInterrupt:  # Ctrl-C: the runs queued are not started (pool.map cancels them), those running end
        interrupted = True
    text = tables(results, [ALL] + wanted)
    (args.out / "table.md").write_text(text + "\n")
    write_atomic(args.out / "results.json", results)
    print(text)
    if interrupted:
        print(f"interrupted: the table holds the runs finished; the same command resumes from {runs}",
              file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
