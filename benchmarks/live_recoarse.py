"""A live fit that goes back to the coarse level as views arrive, against one that never does, step for step.

    python benchmarks/live_recoarse.py [--scenes mug,teddy,demo] [--captures DIR] [--steps-per-view 16]
                                       [--final-steps 35] [--seed 0]
    python benchmarks/live_recoarse.py --capture CAPTURE [--refits JOB_LOG] [--steps-per-view 16] ...

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

**A capture the daemon recorded** (`--capture`: e.g. one that `benchmarks/live.py` keeps, OUT/SCENE/live/captures/SCENE)
is published in its own order (its pose indices are the visiting order), in place of the simulated scenes. With
`--refits` (that capture's live job's log, recon/<job>/job.log) a further row replays the refits the live job made
while the scan ran, at the views and step counts its log records ("live: fitting N of M published views (refit k,
S steps so far, ...)"), then its final run's steps: a wall-clock live run, step for step, whose figures can be set
beside the same capture refitted by the rule at a steady step rate.
"""

from __future__ import annotations

import argparse
import math
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass
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
from spadscan.protocol.child_command import module_command  # noqa: E402
from spadscan.protocol.errors import SpadscanError  # noqa: E402
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
        done = subprocess.run(module_command("spadscan.cli", "simulate", f"builtin:{scene}", "--out", out,
                                             "--sensor", "tmf8820", "--views", scan.views,
                                             "--min-elevation", scan.min_elevation_deg,
                                             "--max-elevation", scan.max_elevation_deg,
                                             "--radius", scan.radius_m, "--no-progress"),
                              stderr=subprocess.PIPE, text=True)
        if done.returncode != 0:
            last = done.stderr.strip().splitlines()[-1:] or [f"exit status {done.returncode}"]
            raise SystemExit(f"live_recoarse.py: error: simulating builtin:{scene} failed: {last[0]}")
    return out


REFIT_LINE = re.compile(r"live: fitting (\d+) of \d+ published views \(refit \d+, (\d+) steps so far")
END_LINE = re.compile(r"live: scan complete \(\d+ views fitted, (\d+) steps\); the final reconstruction "
                      r"continues from the live fit, for (\d+) steps")


@dataclass(frozen=True)
class Refits:
    """A live job's refits as its log records them."""

    at: tuple[tuple[int, int], ...]
    """(views fitted, steps taken before it) at each refit, in order."""
    end_steps: int
    """Steps taken when the scan completed."""
    final_steps: int
    """Steps of the final run, which continued from the live fit."""


def read_refits(log: Path) -> Refits:
    """The refits of a live job's log (recon/<job>/job.log); SystemExit (one line) when it records none, or no final
    run that continued from the live fit (a replay has nothing to set beside it then)."""
    try:
        text = Path(log).read_text(errors="replace")
    except OSError as exc:
        raise SystemExit(f"--refits {log}: cannot read it ({exc.strerror or exc})")
    at = tuple((int(v), int(s)) for v, s in REFIT_LINE.findall(text))
    end = END_LINE.search(text)
    if not at or end is None:
        raise SystemExit(f"--refits {log}: no live refits and final run from the live fit in it (a live job's "
                         f"job.log records them)")
    if any(b[1] < a[1] for a, b in zip(at, at[1:])) or int(end.group(1)) < at[-1][1]:
        raise SystemExit(f"--refits {log}: its step counts go backwards (two jobs' logs in one file?)")
    return Refits(at=at, end_steps=int(end.group(1)), final_steps=int(end.group(2)))


class DaemonOrderScan:
    """Publishes the poses of the complete capture `source` into `dest` one at a time, in the daemon's visiting
    order (pose indices renumbered in that order, as the daemon numbers them). `recorded`: the capture was
    recorded by the daemon, its pose indices already that order (published as they are, whatever its plan)."""

    def __init__(self, source: Path, dest: Path, recorded: bool = False):
        reader = CaptureReader(source)
        data = reader.load()
        index = np.array([m["pose_index"] for m in data.meta])
        indices = np.unique(index)
        by_index = np.stack([data.poses[np.flatnonzero(index == g)[0]] for g in indices])  # a pose's first frame
        if recorded:
            order, planned = indices, by_index
        else:
            plan = build_plan(ScanConfig(), ArmConfig())
            order = np.asarray(plan.description["generated_order"])
            if not (np.array_equal(indices, np.arange(len(order)))
                    and np.allclose(plan.sensor_poses, by_index[order], atol=1e-9)):
                raise SystemExit(f"{source}: its poses are not the daemon's default plan")
            planned = plan.sensor_poses
        self.frames = [np.flatnonzero(index == g).tolist() for g in order]
        self.data = data
        m = reader.manifest
        self.writer = CaptureWriter.create(dest, reader.sensor, rig=m.get("rig"), schedule=m.get("schedule"),
                                           planned_poses=planned, chunk_size=1, scene=m.get("scene"),
                                           frames_per_pose=m.get("frames_per_pose") or 1)
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
    scan = DaemonOrderScan(source, work, recorded=args.capture is not None)
    fit = LiveFit(work, run_config("fast", {}), torch.device("cpu"), args.seed, log=lambda line: None,
                  recoarse=policy)
    while scan.published < scan.planned:
        scan.publish()
        have = fit.views_used
        due = scan.published >= settings.min_views and (
            fit.model is None or refit_due(have, scan.published, math.inf, 0.0, settings))
        if due and scan.published < scan.planned:  # the complete scan goes to the final run
            fit.rebuild(scan.planned)
        fit.train_steps(args.steps_per_view)
    return finish(scan, fit, work, args.final_steps, args, truth)


def replay(source: Path, work: Path, refits: Refits, args, truth) -> dict:
    """The live fit of the recorded capture `source` refitted where a live job's log says it was (the views fitted,
    the steps before each refit), trained to its step count at the scan's end, then its final run's steps."""
    scan = DaemonOrderScan(source, work, recorded=True)
    fit = LiveFit(work, run_config("fast", {}), torch.device("cpu"), args.seed, log=lambda line: None,
                  recoarse=LiveSettings().recoarse)
    for k, (views, _) in enumerate(refits.at):
        while scan.published < views:
            scan.publish()
        fit.rebuild(scan.planned)
        until = refits.at[k + 1][1] if k + 1 < len(refits.at) else refits.end_steps
        fit.train_steps(until - fit.steps)
    while scan.published < scan.planned:
        scan.publish()
    return finish(scan, fit, work, refits.final_steps, args, truth)


def finish(scan: DaemonOrderScan, fit: LiveFit, work: Path, final_steps: int, args, truth) -> dict:
    """The scan completed: Chamfer of the live fit, then of the final run (the preset's model of every view, warm
    from the live fit, for `final_steps`)."""
    scan.writer.finish("complete")
    live = chamfer_mm(fit.mesh(MESH_CELLS), truth, SCORE_POINTS)
    final = fit.warm_factory(fit.continuable)(load_scene(work), run_config("fast", {}), torch.device("cpu"),
                                              RunPlan(steps=None, budget_s=None, seed=args.seed))
    taken = step(final, final_steps)
    return {"live": live, "final": chamfer_mm(final.extract_mesh(MESH_CELLS), truth, SCORE_POINTS),
            "steps": fit.steps + taken, "coarse_restarts": fit.recoarsened, "rebuilds": fit.rebuilds}


def offline(source: Path, steps: int, args, truth) -> dict:
    """The peer: the complete capture fitted from the carved hull for `steps` steps (fewer once converged)."""
    model = make_model(load_scene(source), run_config("fast", {}), torch.device("cpu"),
                       RunPlan(steps=None, budget_s=None, seed=args.seed))
    taken = step(model, steps)
    return {"final": chamfer_mm(model.extract_mesh(MESH_CELLS), truth, SCORE_POINTS), "steps": taken}


def mm(v) -> str:
    return "no surface" if v is None else f"{v:.2f}"


def row(scene: str, name: str, r: dict) -> str:
    """A live fit's row of the table."""
    return (f"| {scene} | {name} | {r['coarse_restarts']} of {r['rebuilds'] - 1} | {mm(r['live'])} | "
            f"{mm(r['final'])} | {r['steps']} |")


def recorded_truth(ap, capture: Path, refits: Refits | None):
    """The ground truth of a --capture, checked before any fit runs (`ap.error`, one line, where it has none, does
    not read, or holds fewer poses than a refit of --refits fitted)."""
    if not (capture / "scan.json").is_file():
        ap.error(f"--capture {capture}: no capture there (no scan.json)")
    try:
        truth = ground_truth(capture)
        poses = len({m["pose_index"] for m in CaptureReader(capture).load().meta})
    except SpadscanError as exc:
        ap.error(f"--capture {capture}: {exc}")
    if truth is None:
        ap.error(f"--capture {capture}: its scene names no ground truth to score against")
    most = 0 if refits is None else max(views for views, _ in refits.at)
    if most > poses:
        ap.error(f"--refits: a refit of {most} views, but --capture {capture} holds {poses} poses")
    return truth


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="mug,teddy,demo", help="built-in scenes, comma-separated")
    ap.add_argument("--captures", type=Path, default=Path("captures-live-recoarse"),
                    help="where the simulated captures are made and kept (default: captures-live-recoarse, in the "
                         "current folder)")
    ap.add_argument("--steps-per-view", type=int, default=16,
                    help="training steps of the live fit per pose published (default 16: what the one-thread live "
                         "fit made per 2.1 s pose)")
    ap.add_argument("--final-steps", type=int, default=35,
                    help="training steps of the final model once the scan is complete (default 35: what the 20 s "
                         "final run made)")
    ap.add_argument("--seed", type=int, default=0, help="seed of every fit, the peer's included (default 0)")
    ap.add_argument("--capture", type=Path, help="a capture the daemon recorded (published in its own order), "
                                                 "in place of --scenes")
    ap.add_argument("--refits", type=Path, help="with --capture: its live job's log (recon/<job>/job.log), whose "
                                                "refits are replayed in a further row")
    args = ap.parse_args(argv)
    if args.steps_per_view < 1 or args.final_steps < 0:
        ap.error("--steps-per-view must be >= 1 and --final-steps >= 0")
    if args.refits is not None and args.capture is None:
        ap.error("--refits replays a recorded capture's live job: give that capture with --capture")
    refits = None if args.refits is None else read_refits(args.refits)
    if args.capture is not None:
        sources = [(args.capture.name, args.capture, recorded_truth(ap, args.capture, refits))]
    else:
        from spadscan.protocol.scenes import BUILTIN_SCENES

        scenes = [scene for scene in args.scenes.split(",") if scene]
        unknown = [scene for scene in scenes if scene not in BUILTIN_SCENES]
        if not scenes or unknown:
            ap.error(f"--scenes {args.scenes!r}: " + (f"no built-in scene {', '.join(unknown)}" if unknown else
                                                        "names no scene") + f" (built-in: {', '.join(BUILTIN_SCENES)})")
        args.captures.mkdir(parents=True, exist_ok=True)
        sources = [(scene, None, None) for scene in scenes]
    torch.set_num_threads(1)
    print(f"fast, one thread, seed {args.seed}; {args.steps_per_view} steps per pose published, "
          f"{args.final_steps} final steps; Chamfer mm ({SCORE_POINTS:,} points)")
    print("| scene | live fit | coarse restarts | at the scan's end | after the final steps | steps |")
    print("|---|---|---|---|---|---|")
    for scene, source, truth in sources:
        if source is None:
            source = simulate(scene, args.captures)
            truth = ground_truth(source)
        rows = []
        for name, policy in (("back to coarse (default)", LiveSettings().recoarse),
                             ("never back to coarse", RecoarsePolicy(growth=0))):
            with tempfile.TemporaryDirectory(prefix="live-recoarse-") as tmp:
                r = follow(source, Path(tmp) / "scan", policy, args, truth)
            rows.append(r)
            print(row(scene, name, r), flush=True)
        if refits is not None:
            with tempfile.TemporaryDirectory(prefix="live-recoarse-") as tmp:
                r = replay(source, Path(tmp) / "scan", refits, args, truth)
            rows.append(r)
            print(row(scene, "the live job's refits, replayed (default)", r), flush=True)
        peer = offline(source, max(r["steps"] for r in rows), args, truth)
        print(f"| {scene} | offline from the hull, every view | - | - | {mm(peer['final'])} | {peer['steps']} |",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
