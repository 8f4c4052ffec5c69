"""A live fit that goes back to the coarse level as views arrive, against one that never does, step for step.

    python benchmarks/live_recoarse.py [--scenes mug,teddy,demo] [--captures DIR] [--steps-per-view 16]
                                       [--final-steps 35] [--seed 0]

For each scene a capture is simulated as the daemon's default scan records it (`spadscan simulate builtin:NAME`: the
TMF8820 model, 128 Fibonacci views from 10 to 80 degrees at 0.5 m; kept in --captures and reused). Its views are
then published one pose at a time, in the daemon's visiting order (`daemon.scan_plan.build_plan` with the [scan] and
[arm] defaults: a nearest-neighbour tour from the highest view), into a new capture that a real `LiveFit` follows:
it refits when the published views have grown as a live job's refits want (`refit_due`'s rule: a quarter more or 16;
the share-of-time rule left out, since time is counted in steps here), and takes --steps-per-view steps for each pose
published (16: what the one-thread live fit of benchmarks/live.py made per 2.1 s pose on the idle 2-core machine).
When the scan is complete, the final model is the preset's model of every view, warm from the live fit (as the live
job's final run), for --final-steps (35: what that 20 s final run made). Rows:

- the live fit as it is (`LiveSettings().recoarse`: back to the coarse level each time the views have grown by half,
  while under half the plan);
- the same with `RecoarsePolicy(growth=0)`: never back to the coarse level (the version before);
- the peer: an offline fit of the complete capture from the carved hull, as many steps in all.

Figures: Chamfer mm (300,000 points) at the scan's end and after the final steps. Step-based, one thread, seeded:
they do not depend on the machine.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from error_vs_time import chamfer_mm, ground_truth  # noqa: E402

from spadscan.daemon.config import ArmConfig, ScanConfig  # noqa: E402
from spadscan.daemon.scan_plan import build_plan  # noqa: E402
from spadscan.protocol.capture_format import Measurement  # noqa: E402
from spadscan.protocol.capture_reader import CaptureReader  # noqa: E402
from spadscan.protocol.capture_writer import CaptureWriter  # noqa: E402
from spadscan.worker.live.job import LiveSettings, refit_due  # noqa: E402
from spadscan.worker.live.live_fit import LiveFit  # noqa: E402
from spadscan.worker.live.recoarse import RecoarsePolicy  # noqa: E402
from spadscan.worker.recon.model_api import RunPlan  # noqa: E402
from spadscan.worker.recon.presets import make_model  # noqa: E402
from spadscan.worker.recon.scene_data import load_scene  # noqa: E402
from spadscan.worker.reconstruct import run_config  # noqa: E402

SCORE_POINTS = 300_000
MESH_CELLS = 256


def simulate(scene: str, captures: Path) -> Path:
    """The daemon's default scan of builtin:`scene`, simulated (made once, then reused)."""
    scan = ScanConfig()
    out = captures / f"{scene}-tmf8820-{scan.views}"
    if not (out / "scan.json").is_file():
        subprocess.run([sys.executable, "-m", "spadscan.cli", "simulate", f"builtin:{scene}", "--out", str(out),
                        "--sensor", "tmf8820", "--views", str(scan.views), "--min-elevation",
                        str(scan.min_elevation_deg), "--max-elevation", str(scan.max_elevation_deg), "--radius",
                        str(scan.radius_m), "--no-progress"], check=True)
    return out


class DaemonOrderScan:
    """Publishes the poses of the complete capture `source` into `dest` one at a time, in the daemon's visiting
    order (pose indices renumbered in that order, as the daemon numbers them)."""

    def __init__(self, source: Path, dest: Path):
        reader = CaptureReader(source)
        data = reader.load()
        generated = np.array([m["pose_index"] for m in data.meta])
        plan = build_plan(ScanConfig(), ArmConfig())
        order = np.asarray(plan.description["generated_order"])
        if not np.allclose(plan.sensor_poses, data.poses[np.argsort(generated)][order], atol=1e-9):
            raise SystemExit(f"{source}: its poses are not the daemon's default plan")
        self.frames = [[i for i in range(len(data.meta)) if generated[i] == g] for g in order]
        self.data = data
        m = reader.manifest
        self.writer = CaptureWriter.create(dest, reader.sensor, rig=m.get("rig"), schedule=m.get("schedule"),
                                           planned_poses=plan.sensor_poses, chunk_size=1, scene=m.get("scene"))
        self.published = 0

    def publish(self) -> None:
        d = self.data
        for i in self.frames[self.published]:
            ref = None if d.reference is None else d.reference[i]
            self.writer.append(Measurement(d.hists[i], d.poses[i], self.published, int(d.meta[i].get("frame", 0)),
                                           ref, {}))
        self.writer.flush()
        self.published += 1

    @property
    def planned(self) -> int:
        return len(self.frames)


def step(model, n: int) -> int:
    """Up to n steps, fewer once the model has converged (a live job stops training then); returns those taken."""
    for k in range(n):
        if model.converged:
            return k
        model.step()
    return n


def follow(source: Path, work: Path, policy: RecoarsePolicy, args, truth) -> dict:
    """The live fit of `source` published in the daemon's order, then its final run; Chamfer at both ends."""
    settings = LiveSettings()
    config = run_config("fast", {})
    scan = DaemonOrderScan(source, work)
    fit = LiveFit(work, config, torch.device("cpu"), args.seed, log=lambda line: None, recoarse=policy)
    steps = 0
    while scan.published < scan.planned:
        scan.publish()
        have = fit.views_used
        due = scan.published >= settings.min_views and (
            fit.model is None or refit_due(have, scan.published, math.inf, 0.0, settings))
        if due and scan.published < scan.planned:  # the complete scan goes to the final run
            fit.rebuild(scan.planned)
        steps += fit.train_steps(args.steps_per_view)
    scan.writer.finish("complete")
    live = chamfer_mm(fit.mesh(MESH_CELLS), truth, SCORE_POINTS)
    final = fit.warm_factory()(load_scene(work), config, torch.device("cpu"),
                               RunPlan(steps=None, budget_s=None, seed=args.seed))
    final_steps = step(final, args.final_steps)
    return {"live": live, "final": chamfer_mm(final.extract_mesh(MESH_CELLS), truth, SCORE_POINTS),
            "steps": steps + final_steps, "coarse_restarts": fit.recoarsened, "rebuilds": fit.rebuilds}


def offline(source: Path, steps: int, args, truth) -> dict:
    """The peer: the complete capture fitted from the carved hull for `steps` steps (fewer once converged)."""
    model = make_model(load_scene(source), run_config("fast", {}), torch.device("cpu"),
                       RunPlan(steps=None, budget_s=None, seed=args.seed))
    taken = step(model, steps)
    return {"final": chamfer_mm(model.extract_mesh(MESH_CELLS), truth, SCORE_POINTS), "steps": taken}


def mm(v) -> str:
    return "no surface" if v is None else f"{v:.2f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="mug,teddy,demo", help="built-in scenes, comma-separated")
    ap.add_argument("--captures", type=Path, default=Path("captures-live-recoarse"),
                    help="where the simulated captures are made and kept")
    ap.add_argument("--steps-per-view", type=int, default=16)
    ap.add_argument("--final-steps", type=int, default=35)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.steps_per_view < 1 or args.final_steps < 0:
        ap.error("--steps-per-view must be >= 1 and --final-steps >= 0")
    torch.set_num_threads(1)
    args.captures.mkdir(parents=True, exist_ok=True)
    print(f"fast, one thread, seed {args.seed}; {args.steps_per_view} steps per pose published, "
          f"{args.final_steps} final steps; Chamfer mm ({SCORE_POINTS:,} points)")
    print("| scene | live fit | coarse restarts | at the scan's end | after the final steps | steps |")
    print("|---|---|---|---|---|---|")
    for scene in [s for s in args.scenes.split(",") if s]:
        source = simulate(scene, args.captures)
        truth = ground_truth(source)
        rows = []
        for name, policy in (("back to coarse (default)", LiveSettings().recoarse),
                             ("never back to coarse", RecoarsePolicy(growth=0))):
            with tempfile.TemporaryDirectory(prefix="live-recoarse-") as tmp:
                r = follow(source, Path(tmp) / "scan", policy, args, truth)
            rows.append(r)
            print(f"| {scene} | {name} | {r['coarse_restarts']} of {r['rebuilds'] - 1} | {mm(r['live'])} | "
                  f"{mm(r['final'])} | {r['steps']} |", flush=True)
        peer = offline(source, max(r["steps"] for r in rows), args, truth)
        print(f"| {scene} | offline from the hull, every view | - | - | {mm(peer['final'])} | {peer['steps']} |",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
