"""Chamfer against the number of views taken: adaptive views (the live ranking and the daemon's choice) against the
Fibonacci schedule, with the same photon budget per view and the same reconstruction budget per fit.

    python benchmarks/next_best_view.py --scenes builtin:cup builtin:lamp builtin:teddy PATH/bunny.obj
        [--measures coverage] [--counts 16,24,32,48,64,96,128] [--steps 1000] [--batch 8] [--live-steps 150]
        [--score 128,64] [--seeds 0,1,2] [--out benchmark-nbv] [--overwrite] [--threads 1]

A scene is `builtin:NAME` or a mesh file (the dataset's bunny.obj), simulated with the dataset's sensor (`lcspc-sim`:
one 15-degree cone, 1024 bins, 5,000 cycles per view) on the daemon's default band: 10-80 degrees of elevation,
0.5 m around the origin.

- `fibonacci` at N views: the daemon's plan of a Fibonacci scan of N views (`scan_plan.build_plan`), simulated.
- `adaptive` (one per --measures): the daemon's adaptive plan of max(--counts) views. Its first min(--counts)
  views are the well-spread initial ones; then the loop a live job and the daemon run, offline: the views so far are
  simulated, the live job's own model (`LiveFit`: refitted warm on the views so far, back to the coarse level as a
  live job's refits go) fits them for --live-steps steps, the first fit --live-first-steps (a field snapshot after
  every third of them), `worker.live.next_views.rank_candidates` ranks the
  candidates with the measure, the ranking is written as next_views.json, and the daemon's own `ViewChooser` (the
  same freshness, spacing and workspace checks as a scan, with the default sim arm) takes the next --batch poses
  from it, one after the other. A real scan ranks every few seconds, about every pose or two; --batch 8 is coarser.
- Every count N of either schedule is then reconstructed from scratch by the `fast` preset for --steps steps (early
  stop off, the learning rate decay laid over the steps after the coarse level, one seed) and scored like
  `spadscan reconstruct` (the 256-cell mesh, 300,000 points per mesh): the same budget for every fit.

Every seed of --seeds is a run of its own: the photon noise of every view, the adaptive loop's live model and every
fit draw from it. One seed's figures move by a millimetre on a concave scene (the cup's 64 Fibonacci views: 3.59,
4.50 and 4.42 mm on seeds 0, 1 and 2), so a comparison rests on several.

Prints one table (scene x schedule: Chamfer in mm at each count, the median over the seeds with their range; the
fewest views of each adaptive run whose median reaches fibonacci's at the largest count) and writes table.md,
results.json and nbv.png into --out. Fits are cached
in results.json (a rerun with the same settings skips them; an adaptive sequence is kept in sequences/), so a killed
run continues where it stopped. An --out whose results.json holds fits made with other settings (--views, --steps,
--batch, --live-steps, --live-first-steps) is refused before anything runs, in one line that says which; --overwrite
discards those fits. Step counts, not seconds: the figures do not depend on the machine's load.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

LIVE_FIRST_STEPS = 400
"""Steps of the first live fit (a cold start: the coarse level and the refinement)."""
SENSOR = "lcspc-sim"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=[], help="builtin:NAME or mesh files")
    p.add_argument("--combine", nargs="+", type=Path, default=[], metavar="FOLDER",
                   help="make the table and plot in --out from the results.json of these earlier --out folders "
                        "(runs split over processes), running nothing")
    p.add_argument("--measures", default="coverage", help="comma-separated ranking measures (coverage, "
                                                          "disagreement, sensitivity)")
    p.add_argument("--counts", default="16,24,32,48,64,96,128", help="views at which both schedules are scored; "
                                                                      "the smallest is the adaptive scan's initial views")
    p.add_argument("--score", default="", help="comma-separated counts to fit in this run (default: all of --counts; "
                                               "a run split over time scores the counts that decide the goal first)")
    p.add_argument("--views", type=int, default=128, help="views of the adaptive scan's plan (default 128)")
    p.add_argument("--steps", type=int, default=1000, help="steps of every scored fit (default 1000)")
    p.add_argument("--batch", type=int, default=8, help="views taken per ranking in the adaptive loop (default 8)")
    p.add_argument("--live-steps", type=int, default=150, help="live-fit steps per ranking (default 150)")
    p.add_argument("--live-first-steps", type=int, default=LIVE_FIRST_STEPS,
                   help=f"steps of the first live fit, a cold start (default {LIVE_FIRST_STEPS})")
    p.add_argument("--seeds", default="0", help="comma-separated seeds, each a run of its own (default 0)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    p.add_argument("--out", type=Path, default=Path("benchmark-nbv"),
                   help="folder for results.json, table.md and nbv.png (default: benchmark-nbv, in the current "
                        "folder)")
    p.add_argument("--overwrite", action="store_true",
                   help="discard the fits cached in --out's results.json (without it, a results.json made with other "
                        "settings is refused)")
    p.add_argument("--no-fibonacci", action="store_true", help="score the adaptive runs only")
    p.add_argument("--no-spread", action="store_true",
                   help="rank by the measure alone, without the spread factor (schedule 'adaptive-MEASURE-nospread')")
    p.add_argument("--unseen-space", action="store_true",
                   help="the coverage measure also weighs space no view has emptied (schedule "
                        "'adaptive-MEASURE-unseen')")
    args = p.parse_args(argv)
    if not args.scenes and not args.combine:
        p.error("give --scenes to run, or --combine FOLDER... to tabulate earlier runs")
    from spadscan.protocol.errors import SpadscanError
    from spadscan.protocol.mesh_io import load_mesh_spec
    from spadscan.worker.live.next_views import MEASURES

    for spec in args.scenes:  # each read now: a misspelt last scene must not fail after hours of the first ones' fits
        try:
            load_mesh_spec(spec)
        except SpadscanError as exc:
            p.error(f"--scenes {spec}: {exc}")

    args.measures = [m for m in args.measures.split(",") if m]
    bad = [m for m in args.measures if m not in MEASURES]
    if bad:
        p.error(f"unknown measure {bad[0]!r} (known: {', '.join(MEASURES)})")
    try:
        args.counts = sorted({int(c) for c in args.counts.split(",")})
    except ValueError:
        p.error(f"--counts {args.counts!r} must be comma-separated integers")
    try:
        args.seeds = sorted({int(c) for c in args.seeds.split(",") if c})
    except ValueError:
        p.error(f"--seeds {args.seeds!r} must be comma-separated integers")
    if not args.seeds:
        p.error("--seeds names no seed")
    try:
        args.score = sorted({int(c) for c in args.score.split(",") if c} or args.counts, reverse=True)
    except ValueError:
        p.error(f"--score {args.score!r} must be comma-separated integers")
    if not set(args.score) <= set(args.counts):
        p.error(f"--score {args.score} must be among --counts {args.counts}")
    if args.counts[-1] > args.views:
        p.error(f"--counts go up to {args.counts[-1]}, beyond the plan's --views {args.views}")
    if args.counts[0] < 4 or args.steps < 1 or args.batch < 1 or min(args.live_steps, args.live_first_steps) < 3:
        p.error("--counts must be >= 4, --steps and --batch >= 1, --live-steps and --live-first-steps >= 3")
    why = out_problem(args)
    if why:
        p.error(why)
    return args


SETTING_FLAGS = {"views": "--views", "steps": "--steps", "batch": "--batch", "live_steps": "--live-steps",
                 "live_first_steps": "--live-first-steps", "sensor": "sensor"}
"""The option behind each of `settings_of`'s fields, as a refusal names them."""


def out_problem(args) -> str | None:
    """Why --out cannot take this run (one line), or None. Reads, never writes: the fits an earlier run cached there
    cost minutes each, so fits made with other settings are never silently dropped (--overwrite drops them)."""
    from spadscan.protocol.folders import folder_problem

    if args.out.exists() and not args.out.is_dir():
        return f"--out {args.out}: exists and is not a folder"
    if (unmakeable := folder_problem(args.out)) is not None:
        return f"--out {args.out}: {unmakeable}"
    path = args.out / "results.json"
    if args.combine or args.overwrite or not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
        recorded, held = data.get("settings"), len(data["fits"])
    except (OSError, ValueError, AttributeError, KeyError, TypeError) as exc:
        return (f"--out {args.out}: its results.json does not read as this script's ({exc}): choose another --out, "
                "or pass --overwrite to replace it")
    wanted = settings_of(args)
    if recorded in (None, wanted):
        return None
    diffs = [f"{SETTING_FLAGS.get(k, k)} {recorded.get(k) if isinstance(recorded, dict) else None}, not {wanted[k]}"
             for k in wanted if not isinstance(recorded, dict) or recorded.get(k) != wanted[k]]
    return (f"--out {args.out} holds {held} fits made with other settings ({'; '.join(diffs) or recorded}): choose "
            "another --out, or pass --overwrite to discard them")


# ---- scenes and captures ------------------------------------------------------------------------------------------
class Scene:
    """A mesh, its ground truth and its simulator."""

    def __init__(self, spec: str, seed: int):
        from spadscan.protocol.mesh_io import load_mesh_spec
        from spadscan.protocol.sensor_presets import sensor_preset
        from spadscan.protocol.simulator import SimSettings, Simulator
        from spadscan.worker.ground_truth import load_ground_truth

        self.spec = spec
        self.name = spec.split(":", 1)[1] if spec.startswith("builtin:") else Path(spec).stem
        self.mesh, self.record = load_mesh_spec(spec)
        self.truth = load_ground_truth(spec)
        self.seed = seed
        self.sim = Simulator(self.mesh, sensor_preset(SENSOR), SimSettings(), seed)

    def frames(self, poses: np.ndarray) -> np.ndarray:
        """Histograms (n, Z, B) of these views, their photon noise drawn from a seed of the views themselves: the
        same views give the same counts whatever ran before."""
        from spadscan.protocol.simulator import Simulator

        sim = Simulator(self.mesh, self.sim.base_sensor, self.sim.settings, (int(digest(poses), 16) + self.seed)
                        % 2**63)
        return sim.frames(poses).hists

    def capture(self, folder: Path, poses: np.ndarray, hists: np.ndarray) -> Path:
        """A complete capture of these views (written afresh)."""
        import shutil

        from spadscan.protocol.capture_format import Measurement
        from spadscan.protocol.capture_writer import CaptureWriter

        shutil.rmtree(folder, ignore_errors=True)
        w = CaptureWriter.create(folder, self.sim.sensor, rig={"kind": "simulated"}, planned_poses=poses,
                                 chunk_size=256, scene=dict(self.record))
        for i, (p, h) in enumerate(zip(poses, hists)):
            w.append(Measurement(h, p, i, 0, None, {"simulated": True}))
        w.finish("complete")
        return folder


def scan_config(schedule: str, views: int, initial: int, batch: int):
    from spadscan.daemon.config import ScanConfig, scan_with

    # The lag allows a ranking --batch poses old; a scan refuses a lag below 2 (the freshest ranking is one pose
    # behind when a daemon chooses), and this loop ranks before each batch, so 2 admits every ranking of --batch 1.
    extra = {"initial_views": initial, "next_views_max_lag": max(2, batch), "next_views_max_age_s": 86_400.0}
    return scan_with(ScanConfig(), {"schedule": schedule, "views": views, **(extra if schedule == "adaptive" else {})})


def fibonacci_poses(views: int) -> np.ndarray:
    from spadscan.daemon.config import ArmConfig
    from spadscan.daemon.scan_plan import build_plan

    return build_plan(scan_config("fibonacci", views, 0, 1), ArmConfig()).sensor_poses


# ---- fits ---------------------------------------------------------------------------------------------------------
def fit_config(steps: int):
    from spadscan.worker.reconstruct import run_config

    coarse = 300
    return run_config("fast", {"early_stop": False, "schedule.fine_steps": max(1, steps - coarse)})


def score_fit(capture: Path, truth, steps: int, seed: int) -> dict:
    """Reconstruct `capture` from scratch for `steps` steps; Chamfer and its parts (mm) against `truth`. A fit that
    leaves no surface (too few views can let it empty the grid) is a result too: chamfer_mm None and `failed` says
    why, so one such point does not end the benchmark."""
    import torch

    from spadscan.worker.recon.errors import ReconstructionError
    from spadscan.worker.reconstruct import set_up_run

    config = fit_config(steps)
    t0 = time.perf_counter()
    run = set_up_run(capture, config, torch.device("cpu"), steps=steps, budget_s=None, seed=seed, log=lambda s: None)
    for _ in range(steps):
        run.model.step()
    fit_s = time.perf_counter() - t0
    try:
        mesh = run.model.extract_mesh(config.mesh_resolution)
    except ReconstructionError as exc:
        return {"chamfer_mm": None, "failed": str(exc), "steps": steps, "fit_seconds": round(fit_s, 1)}
    m = truth.metrics(mesh, n_points=config.metrics_points)  # the metrics' fixed seed: the run's moves the fit alone
    return {"chamfer_mm": m.chamfer_mm, "accuracy_mm": m.accuracy_mm, "completeness_mm": m.completeness_mm,
            "steps": steps, "fit_seconds": round(fit_s, 1)}


class LiveLoop:
    """The live model of the adaptive loop: a live job's own `LiveFit` on the views so far (refitted warm, back to the
    coarse level as a live job's refits go), stepped for a number of steps where a live job counts seconds."""

    def __init__(self, planned: int, seed: int):
        self.fit, self.planned, self.seed = None, planned, seed

    @property
    def steps(self) -> int:
        return 0 if self.fit is None else self.fit.steps

    def snapshot(self, capture: Path, steps: int):
        """Refit on the views of `capture` (always the same folder, rewritten with more views), step, and return the
        live state the ranking reads: the field after each third of the steps."""
        import torch

        from spadscan.worker.live.live_fit import LiveFit

        if self.fit is None:
            self.fit = LiveFit(capture, fit_config(10_000), torch.device("cpu"), self.seed, log=lambda line: None)
        if not self.fit.rebuild(self.planned):
            raise SystemExit(f"the live fit cannot fit the {capture} views so far")
        for third in range(3):
            self.fit.train_steps(steps // 3 + (steps % 3 if third == 2 else 0))
            self.fit.remember()
        return self.fit.snapshot()


def adaptive_sequence(scene: Scene, measure: str, views: int, initial: int, upto: int, args, work: Path) -> dict:
    """The first `upto` poses an adaptive scan of `views` takes on `scene` (see the module docstring) and why each
    was taken."""
    from spadscan.daemon.adaptive import ViewChooser
    from spadscan.daemon.config import ArmConfig, scan_to_dict
    from spadscan.daemon.scan_plan import build_plan
    from spadscan.protocol.next_views import candidate_poses, ranked, write_next_views
    from spadscan.worker.live.next_views import rank_candidates

    arm = ArmConfig()
    scan = scan_config("adaptive", views, initial, args.batch)
    plan = build_plan(scan, arm).sensor_poses
    live = work / "live"
    live.mkdir(parents=True, exist_ok=True)
    chooser = ViewChooser(scan, arm, arm.hand_eye, live)
    candidates = candidate_poses(scan_to_dict(scan))
    why, poses = [], []
    loop = LiveLoop(views, scene.seed)
    rank_s = []
    while len(poses) < upto:
        n = len(poses)
        if n >= initial:
            capture = scene.capture(work / "stage", np.array(poses), scene.frames(np.array(poses)))
            snap = loop.snapshot(capture, args.live_first_steps if loop.fit is None else args.live_steps)
            t0 = time.perf_counter()
            scores = rank_candidates(snap, candidates, measure, spread=not args.no_spread,
                                     unseen_space=args.unseen_space)
            rank_s.append(time.perf_counter() - t0)
            write_next_views(live, ranked(candidates, scores, n, measure))
        for i in range(n, min(upto, n + (initial if n < initial else args.batch))):
            choice, plan = chooser.choose(plan, i)
            poses.append(choice.pose)
            why.append(choice.why)
    poses = np.array(poses)
    return {"poses": poses, "why": why, "rank_seconds": float(np.mean(rank_s)) if rank_s else 0.0,
            "live_steps": loop.steps}


def digest(poses: np.ndarray) -> str:
    return hashlib.sha256(np.round(np.asarray(poses), 9).tobytes()).hexdigest()[:16]


# ---- the run --------------------------------------------------------------------------------------------------------
class Results:
    """results.json: every fit, keyed by scene, schedule, count and seed (`fit_key`), with the settings that made
    it."""

    def __init__(self, path: Path, settings: dict, overwrite: bool = False):
        """`overwrite`: start afresh, whatever `path` holds. Otherwise its fits must have been made with `settings`
        (`out_problem` refuses any other before the run starts): ValueError if not, never a silent reset."""
        self.path, self.settings = path, settings
        self.data = json.loads(path.read_text()) if path.is_file() and not overwrite else {"fits": {}}
        if self.data.get("settings") not in (None, settings):
            raise ValueError(f"{path}: its fits were made with other settings ({self.data.get('settings')})")
        self.data["settings"] = settings

    def get(self, key: str, poses_digest: str) -> dict | None:
        """The fit of `key`, also one made under another key of the same scene and seed with the same views (the
        adaptive runs share their initial views); None when there is none."""
        entry = self.data["fits"].get(key)
        if entry is not None and entry.get("poses_digest") == poses_digest:
            return entry
        scene, *_, seed = key.split("|")
        for other, e in self.data["fits"].items():
            o_scene, *_, o_seed = other.split("|")
            if (o_scene, o_seed) == (scene, seed) and e.get("poses_digest") == poses_digest:
                self.put(key, dict(e))
                return e
        return None

    def put(self, key: str, entry: dict) -> None:
        self.data["fits"][key] = entry
        tmp = self.path.with_name(".tmp-" + self.path.name)
        tmp.write_text(json.dumps(self.data, indent=1))
        tmp.replace(self.path)


def fit_key(scene: str, schedule: str, n: int, seed: int) -> str:
    return f"{scene}|{schedule}|{n}|{seed}"


def settings_of(args) -> dict:
    """What every fit of a run depends on besides its scene, schedule, count and seed."""
    return {"views": args.views, "steps": args.steps, "batch": args.batch, "live_steps": args.live_steps,
            "sensor": SENSOR, "live_first_steps": args.live_first_steps}


def run(args) -> dict:
    import torch

    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    results = Results(args.out / "results.json", settings_of(args), overwrite=args.overwrite)
    for seed in args.seeds:
        for spec in args.scenes:
            run_scene(Scene(spec, seed), args, results)
    return results.data


def run_scene(scene: Scene, args, results: Results) -> None:
    """Both schedules' fits of one scene and seed at the counts of --score, those not in `results` yet."""
    seed = scene.seed
    initial = min(args.counts)
    work = args.out / "work" / f"{scene.name}-s{seed}"
    if not args.no_fibonacci:
        for n in args.score:
            poses = fibonacci_poses(n)
            key = fit_key(scene.name, "fibonacci", n, seed)
            if results.get(key, digest(poses)) is None:
                hists = scene.frames(poses)
                entry = score_fit(scene.capture(work / "fit", poses, hists), scene.truth, args.steps, seed)
                results.put(key, {**entry, "poses_digest": digest(poses)})
                print(f"{key}: {chamfer_text(entry)}", file=sys.stderr)
    for measure in args.measures:
        seq = sequence(scene, measure, initial, max(args.counts), args, work)
        label = f"adaptive-{measure}{variant_suffix(args)}"
        for n in args.score:
            poses = seq["poses"][:n]
            key = fit_key(scene.name, label, n, seed)
            if results.get(key, digest(poses)) is None:
                hists = scene.frames(poses)
                entry = score_fit(scene.capture(work / "fit", poses, hists), scene.truth, args.steps, seed)
                counts = {w: seq["why"][:n].count(w) for w in ("initial", "adaptive", "fallback")}
                results.put(key, {**entry, "poses_digest": digest(poses), "view_choices": counts,
                                  "rank_seconds": seq["rank_seconds"]})
                print(f"{key}: {chamfer_text(entry)}", file=sys.stderr)


def variant_suffix(args) -> str:
    """How the ranking differs from the default, in schedule names and sequence file names."""
    return ("-nospread" if args.no_spread else "") + ("-unseen" if args.unseen_space else "")


def sequence(scene: Scene, measure: str, initial: int, upto: int, args, work: Path) -> dict:
    """The adaptive sequence's first `upto` poses, from sequences/ when a run with the same settings made as many."""
    folder = args.out / "sequences"
    folder.mkdir(exist_ok=True)
    # "live2": sequences of the live loop that is the live job's LiveFit (earlier ones are not reused).
    tag = (f"{scene.name}-{measure}{variant_suffix(args)}-{args.views}-{initial}-b{args.batch}-l{args.live_steps}"
           f"-f{args.live_first_steps}-s{scene.seed}-live2")
    path = folder / f"{tag}.npz"
    if path.is_file():
        saved = np.load(path, allow_pickle=False)
        if len(saved["poses"]) >= upto:
            return {"poses": saved["poses"], "why": saved["why"].tolist(),
                    "rank_seconds": float(saved["rank_seconds"])}
    t0 = time.perf_counter()
    seq = adaptive_sequence(scene, measure, args.views, initial, upto, args, work / measure)
    print(f"{scene.name} {measure}: first {upto} views of {args.views} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    np.savez(path, poses=seq["poses"], why=np.array(seq["why"]), rank_seconds=seq["rank_seconds"])
    return seq


# ---- the table and the plot ---------------------------------------------------------------------------------------
def chamfer_text(entry: dict) -> str:
    return "no surface" if entry.get("chamfer_mm") is None else f"{entry['chamfer_mm']:.2f} mm"


def by_count(data: dict) -> dict[tuple[str, str], dict[int, list]]:
    """{(scene, schedule): {count: [Chamfer mm or None (no surface), one per seed]}} of a results.json's fits."""
    rows: dict[tuple[str, str], dict[int, list]] = {}
    for key, entry in sorted(data["fits"].items()):
        scene, schedule, n, _seed = key.split("|")
        rows.setdefault((scene, schedule), {}).setdefault(int(n), []).append(entry["chamfer_mm"])
    return rows


def worst_if_none(chamfer_mm: float | None) -> float:
    """A fit with no surface (None) ranks as the worst."""
    return np.inf if chamfer_mm is None else chamfer_mm


def median(values: list) -> float | None:
    """The median Chamfer of the seeds; None when that is a fit with no surface."""
    m = float(np.median([worst_if_none(v) for v in values]))
    return None if not np.isfinite(m) else m


def cell(values: list) -> str:
    """One seed's Chamfer, or the seeds' median and range ('no surface' for a fit that left none)."""
    m = median(values)
    text = "no surface" if m is None else f"{m:.2f}"
    if len(values) > 1:
        ends = (min(values, key=worst_if_none), max(values, key=worst_if_none))
        text += " (" + "-".join("no surface" if v is None else f"{v:.2f}" for v in ends) + ")"
    return text


def table(data: dict) -> str:
    rows = by_count(data)
    counts = sorted({n for by_n in rows.values() for n in by_n})
    seeds = sorted({int(k.split("|")[3]) for k in data["fits"]})
    head = "| scene | schedule | " + " | ".join(str(c) for c in counts) + f" | views to fibonacci@{counts[-1]} |"
    lines = [head, "|" + "---|" * (len(counts) + 3)]
    for (scene, schedule), by_n in sorted(rows.items()):
        goal = median(rows.get((scene, "fibonacci"), {}).get(counts[-1], [None]))
        reach = "-"
        if goal is not None and schedule != "fibonacci":
            hit = [n for n in counts if n in by_n and median(by_n[n]) is not None and median(by_n[n]) <= goal]
            reach = str(hit[0]) if hit else f"> {max(by_n)}"
        cells = ["" if c not in by_n else cell(by_n[c]) for c in counts]
        lines.append(f"| {scene} | {schedule} | " + " | ".join(cells) + f" | {reach} |")
    if len(seeds) > 1:
        lines.append(f"\nChamfer in mm, the median of seeds {', '.join(map(str, seeds))} (their range in brackets).")
    return "\n".join(lines)


def plot(data: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    series: dict[str, dict[str, dict[int, list]]] = {}
    for (scene, schedule), by_n in by_count(data).items():
        series.setdefault(scene, {})[schedule] = by_n
    fig, axes = plt.subplots(1, len(series), figsize=(4.2 * len(series), 3.6), squeeze=False)
    for ax, (scene, by_schedule) in zip(axes[0], sorted(series.items())):
        for schedule, pts in sorted(by_schedule.items()):
            n = sorted(k for k in pts if median(pts[k]) is not None)  # a fit with no surface has no Chamfer to draw
            mid = np.array([median(pts[k]) for k in n])
            lo = np.array([min(v for v in pts[k] if v is not None) for k in n])
            hi = np.array([max(v for v in pts[k] if v is not None) for k in n])
            ax.errorbar(n, mid, yerr=[mid - lo, hi - mid] if len(n) else None, marker="o", capsize=3, label=schedule)
        ax.set_xscale("log", base=2)
        ax.set_xticks(sorted({k for pts in by_schedule.values() for k in pts}))
        ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())  # 64, not 2^6
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        ax.set_title(scene)
        ax.set_xlabel("views taken")
        ax.set_ylabel("Chamfer (mm): median, range over seeds")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def combine(folders: list[Path]) -> dict:
    """The fits of several runs' results.json in one (runs split over processes or seeds; their settings must
    agree). A run made before the seed was part of every key held one seed, its settings' "seed"."""
    data = {"fits": {}}
    for folder in folders:
        if not (folder / "results.json").is_file():
            raise SystemExit(f"{folder}: no results.json here (--combine takes the folders that earlier runs "
                             "wrote with --out)")
        part = json.loads((folder / "results.json").read_text())
        settings = dict(part["settings"])
        seed = settings.pop("seed", 0)
        if data.get("settings") not in (None, settings):
            raise SystemExit(f"{folder}: made with other settings ({part['settings']}) than {folders[0]}")
        data["settings"] = settings
        for key, entry in part["fits"].items():
            data["fits"][key if key.count("|") == 3 else f"{key}|{seed}"] = entry
    return data


def main(argv=None) -> int:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        data = combine(args.combine) if args.combine else run(args)
    except KeyboardInterrupt:
        print(f"next_best_view.py: interrupted: {args.out / 'results.json'} keeps the fits that finished, and the "
              f"same command goes on from them", file=sys.stderr)
        return 130
    text = table(data)
    print(text)
    (args.out / "table.md").write_text(text + "\n")
    plot(data, args.out / "nbv.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
