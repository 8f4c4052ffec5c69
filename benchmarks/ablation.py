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

Writes runs/<scene>--<variant>.json as each run ends, with the settings it ran with (the scene folder it was made
from, --steps, --seed, --threads, --points, --device and its --set overrides). A scene is named by its folder's name:
two scenes of the same name are refused. A later call with the same --out reuses the runs made with its own
settings, so an interrupted ablation resumes where it stopped (Ctrl-C, or SIGTERM, writes the table of the runs
finished: a run it stopped did not fail, it is not run, "-", and the exit status is 130; Ctrl-Z pauses the runs with
the script, fg or bg goes on with them); an
--out holding a run made with other settings (another scene folder of the same name included) is refused, in one line
that says which (--overwrite starts afresh). Then table.md: per part and scene, the Chamfer (mm) and the mean normal
error (degrees) with the part off, against all parts on, and the steps each run took.

A run that fails is "failed" in the table (results.json: {"failed": its last line of error}), is not kept in runs/
(the same command runs it again), and the exit status is then 1; where a scene's all-parts run failed, its parts are
not run ("-"). --device cuda without a CUDA device is refused before any run.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from error_vs_time import ground_truth, prepare_scene, scene_problem, source_commit, write_atomic  # noqa: E402

from spadscan import parent_watch  # noqa: E402

ALL = "all parts"


DERIVED = ("average", "plateau")
"""Parts whose ablation the all-parts run gives without a run of its own: neither changes the fit. Without the
average the mesh comes from the grid as it is (the same fit, meshed from its last step); without the plateau test
the run goes on to --steps (the same fit up to the early stop, continued)."""


SETTINGS = {"scene": "--scenes", "steps": "--steps", "seed": "--seed", "threads": "--threads", "points": "--points",
            "device": "--device", "overrides": "--set"}
"""What a run's figures depend on besides the code, and the option that sets each. The scene is its folder's resolved
path: runs/ names a run by the folder's name alone, which another folder (a second batch of captures) can share."""


def settings_of(scene: str, steps: int, seed: int, threads: int, points: int, device: str,
                overrides: list[str]) -> dict:
    """A run's settings (SETTINGS) as its file records them."""
    return {"scene": scene, "steps": steps, "seed": seed, "threads": threads, "points": points, "device": device,
            "overrides": list(overrides)}


def scene_key(scene: Path) -> str:
    """How a run's settings name the scene folder it was made from."""
    return str(scene.resolve())


def variant_overrides(overrides: list[str], variant: str) -> list[str]:
    """The --set overrides of a variant's run: the call's, and the part switched off."""
    return list(overrides) + ([] if variant == ALL else [f"parts.{variant}.enabled=false"])


def other_settings(recorded: dict | None, wanted: dict) -> str | None:
    """How a run file's recorded settings differ from `wanted` ('--steps 5, not 40'), or None when they do not."""
    if not isinstance(recorded, dict):
        return "no settings recorded (made before they were)"

    def shown(key, value):
        if value is None:
            return "none recorded"
        return (" ".join(value) or "none") if key == "overrides" and isinstance(value, list) else value

    diffs = [f"{flag} {shown(key, recorded.get(key))}, not {shown(key, wanted[key])}"
             for key, flag in SETTINGS.items() if recorded.get(key) != wanted[key]]
    return "; ".join(diffs) or None


def run_one(capture: Path, steps: int, seed: int, threads: int, overrides: list[str], points: int = 300_000,
            device: str = "cpu", scene: str | None = None) -> dict:
    """One step-based run of the fast preset on `capture`, scored against its ground truth. A run with every part
    that runs also scores the `DERIVED` ablations (`derived`: part -> the same fields). `scene`: the scene folder
    its settings name (the capture's own path by default; a dataset scene's capture is an import of it)."""
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
            # The metrics' own fixed seed (0), not the run's: scored on the samples `spadscan reconstruct` uses.
            m = truth.metrics(model.extract_mesh(config.mesh_resolution, averaged=averaged), n_points=points)
            record.update(chamfer_mm=m.chamfer_mm, accuracy_mm=m.accuracy_mm, completeness_mm=m.completeness_mm,
                          normal_error_deg=m.normal_error_deg, fscore_5mm=m.fscore_5mm)
        return record

    out = scored({"steps": result.steps, "stopped_by": result.stopped_by, "train_s": result.seconds,
                  "setup_s": run.setup_s, "overrides": overrides, "summary": model.summary(),
                  "commit": source_commit(), "config": config.to_dict(), "threads": threads, "device": device,
                  "settings": settings_of(scene or scene_key(capture), steps, seed, threads, points, device,
                                          overrides)})
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


# A run ended by one of these signals was stopped, not failed: by `Children.stop` (SIGTERM), or by a Ctrl-C that
# reached it in the instant between its fork and its move to a group of its own, which may end before this script's
# own KeyboardInterrupt has called `stop`; or by a user's `kill` of that one run. The same command runs it again.
STOPPED_BY = (-signal.SIGINT, -signal.SIGTERM)


class Children:
    """The runs' processes. Each runs in a process group of its own, so that Ctrl-C, which the terminal sends to the
    foreground job's group, reaches only this script, which then stops them itself (`stop`): a run that ends after
    that was stopped, not failed. A child's own exit status cannot say so (a KeyboardInterrupt in the middle of an
    import ends it as an error of that import, exit status 1), and a worker thread never sees the KeyboardInterrupt,
    which reaches only the main thread. Ctrl-Z, which the terminal sends to the same group, this script passes on
    (`pause`). Killed outright, this script cannot stop them: each then stops by itself
    (spadscan/parent_watch.py), and one stopped by Ctrl-Z is hung up by the kernel (a stopped group that loses its
    last parent in the session)."""

    def __init__(self):
        # Re-entrant: `pause` runs as a signal handler in the main thread, which may hold it already (in `stop`).
        self.lock = threading.RLock()
        self.running: set[subprocess.Popen] = set()
        self.stopped = False

    def start(self, cmd: list[str], env: dict) -> subprocess.Popen | None:
        """`cmd` started, or None once `stop` was called (no run starts after it)."""
        with self.lock:
            if self.stopped:
                return None
            # A group of its own, in this script's session: the kernel hangs up the runs of an ablation killed
            # while paused, which a session of their own would leave stopped for good. SIGTSTP blocked in this
            # thread while it starts one (the child inherits the mask): a Ctrl-Z between the child's fork and its
            # exec, while the child is still in this script's group, would stop it there and, a vfork child, this
            # thread with it, which holds the lock `pause` waits for. A run is paused by SIGSTOP, never SIGTSTP.
            blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTSTP})
            try:
                proc = subprocess.Popen(cmd, env=parent_watch.child_env(env), stdin=subprocess.DEVNULL,
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, process_group=0)
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
            self.running.add(proc)
            return proc

    def done(self, proc: subprocess.Popen) -> None:
        with self.lock:
            self.running.discard(proc)

    def stop(self) -> None:
        """Stop every run (SIGTERM) and start none after."""
        with self.lock:
            self.stopped = True
            for proc in self.running:
                proc.terminate()

    def pause(self, signum: int) -> None:
        """Ctrl-Z (`signum`, SIGTSTP): stop every run, then this script, as the terminal stops a job; continued (fg,
        bg), continue the runs. Until then no run starts or ends unseen (the lock is held)."""
        with self.lock:
            self.signal_runs(signal.SIGSTOP)  # cannot be caught or ignored: a run stops whatever it is doing
            try:
                stop_self(signum)
            finally:
                self.signal_runs(signal.SIGCONT)

    def signal_runs(self, signum: int) -> None:
        """`signum` to every run's process group (the run and what it started); a run that has ended is skipped."""
        for proc in self.running:
            if proc.returncode is None:
                with contextlib.suppress(ProcessLookupError):  # ended, not yet reaped
                    os.killpg(proc.pid, signum)


def stop_self(signum: int) -> None:
    """Stop this process as `signum` stops one that does not catch it (the shell then says "Stopped"); returns once
    it is continued."""
    handler = signal.signal(signum, signal.SIG_DFL)
    try:
        signal.raise_signal(signum)  # to this thread: taken (the process stopped) before raise_signal returns
    finally:
        signal.signal(signum, handler)


def run_in_child(capture: Path, target: Path, args, overrides: list[str], scene: str,
                 children: Children | None = None) -> dict | None:
    """Run `run_one` in a fresh process (clean memory, nothing shared) started by `children`; its result,
    {"failed": why} (the child's last line of error) when it failed, or None when `children` was stopped before it
    ended: not run."""
    children = Children() if children is None else children
    cmd = [sys.executable, __file__, "--one", str(capture), "--result", str(target), "--steps", str(args.steps),
           "--seed", str(args.seed), "--threads", str(args.threads), "--points", str(args.points),
           "--device", args.device, "--recorded-scene", scene]
    cmd += [f"--set={o}" for o in overrides]
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    proc = children.start(cmd, env)
    if proc is None:
        return None
    try:
        stdout, stderr = proc.communicate()
    finally:
        children.done(proc)
    if proc.returncode == 0 and target.is_file():
        return json.loads(target.read_text())
    if children.stopped or proc.returncode in STOPPED_BY:
        return None
    tail = (stderr or stdout).strip().splitlines()
    return {"failed": tail[-1] if tail else f"exit status {proc.returncode}"}


def failed(res: dict | None) -> bool:
    return res is not None and "failed" in res


def parts_that_ran(result: dict) -> list[str]:
    return list(result["summary"].get("parts", {}))


def fmt(v, digits=2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def cell(res: dict | None, base: dict | None, key: str, digits: int) -> str:
    """'value (+delta)' of a run against the all-parts run; '-' where it did not run, 'failed' where it failed."""
    if failed(res):
        return "failed"
    if res is None or res.get(key) is None:
        return "-"
    if base is None or failed(base) or base is res or base.get(key) is None:
        return fmt(res[key], digits)
    return f"{fmt(res[key], digits)} ({res[key] - base[key]:+.{digits}f})"


def scene_cell(runs: dict, variant: str, key: str, digits: int) -> str:
    """A scene's cell of `variant`. 'n/a' only where the all-parts run says the part does not run there: where that
    run failed or never ran, nothing is known of the parts ('-')."""
    base = runs.get(ALL)
    if runs.get(variant) is None and variant != ALL and base is not None and not failed(base) \
            and variant not in runs.get("_ran", []):
        return "n/a"
    return cell(runs.get(variant), base, key, digits)


def tables(results: dict[str, dict[str, dict]], variants: list[str]) -> str:
    scenes = list(results)
    lines = []
    for title, key, digits in (("Chamfer (mm), part off (change against all parts on)", "chamfer_mm", 2),
                               ("Mean normal error (degrees), part off (change)", "normal_error_deg", 1),
                               ("Steps (early stop)", "steps", 0)):
        lines += [f"### {title}", "", "| part off | " + " | ".join(scenes) + " |",
                  "|---|" + "---|" * len(scenes)]
        for v in variants:
            lines.append(f"| {v} | " + " | ".join(scene_cell(results[s], v, key, digits) for s in scenes) + " |")
        lines.append("")
    lines.append("n/a: the part does not run on that scene (see the all-parts run's report, `model.parts_left_out`).")
    if any(failed(r) for runs in results.values() for r in runs.values() if isinstance(r, dict)):
        lines.append("failed: the run failed (results.json says why); -: not run (a scene whose all-parts run failed "
                     "ablates nothing).")
    return "\n".join(lines)


def failures(results: dict[str, dict[str, dict]]) -> list[str]:
    """'scene variant (why)' of every run that failed."""
    return [f"{name} {variant} ({res['failed']})" for name, runs in results.items()
            for variant, res in runs.items() if isinstance(res, dict) and failed(res)]


def out_problem(out: Path) -> str | None:
    """Why --out cannot hold runs/, table.md and results.json (one line), or None."""
    if out.exists() and not out.is_dir():
        return f"--out {out}: exists and is not a folder"
    if (out / "runs").exists() and not (out / "runs").is_dir():
        return f"--out {out}: its runs exists and is not a folder"
    return unmakeable(out)


def unmakeable(out: Path) -> str | None:
    """'--out OUT: cannot create it (...)' where this user cannot make or write into the folder, else None."""
    from spadscan.protocol.folders import folder_problem

    reason = folder_problem(out)
    return None if reason is None else f"--out {out}: {reason}"


def scenes_problem(scenes: list[Path]) -> str | None:
    """Why the scenes cannot be ablated together (one line), or None: runs/ names a scene's runs by its folder's
    name, so two folders of one name would share (or silently replace) each other's runs."""
    names: dict[str, Path] = {}
    for scene in scenes:
        name = scene.resolve().name
        if name in names:
            if names[name].resolve() == scene.resolve():
                return f"scene {scene} is named twice"
            return (f"scenes {names[name]} and {scene} share the name {name!r} (their runs would share "
                    f"runs/{name}--VARIANT.json): ablate them with different --out folders")
        names[name] = scene
    return None


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
    parser.add_argument("--recorded-scene", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one is not None:
        parent_watch.watch_parent_from_env()  # killed outright, the ablation cannot stop this run: it stops itself
        write_atomic(args.result, run_one(args.one, args.steps, args.seed, args.threads, args.overrides, args.points,
                                          args.device, args.recorded_scene))
        return 0
    if not args.scenes or args.out is None:
        parser.error("--scenes and --out are required")
    if args.steps < 1 or args.threads < 1 or args.jobs < 1 or args.seed < 0 or not 1000 <= args.points <= 1_000_000:
        parser.error("--steps, --threads and --jobs must be >= 1, --seed >= 0 and --points in [1000, 1000000]")
    from spadscan.worker.recon.config import parse_override
    from spadscan.worker.recon.fast.parts import PARTS
    from spadscan.worker.reconstruct import resolve_device, run_config
    from spadscan.protocol.errors import SpadscanError

    names = [cls.name for cls in PARTS]
    wanted = [p for p in args.parts.split(",") if p] or names
    unknown = sorted(set(wanted) - set(names))
    if unknown:
        parser.error(f"--parts: no part {', '.join(unknown)} (parts: {', '.join(names)})")
    try:
        run_config("fast", dict(parse_override(text) for text in args.overrides))
        resolve_device(args.device)  # cuda without a CUDA device: every run would start, and fail
    except SpadscanError as exc:
        parser.error(str(exc))
    for scene in args.scenes:
        why = scene_problem(scene)
        if why:
            parser.error(why)
    why = scenes_problem(args.scenes) or out_problem(args.out)
    if why:
        parser.error(why)
    runs = args.out / "runs"
    if args.overwrite and runs.exists():
        for f in runs.glob("*.json"):
            f.unlink()

    def target_of(name: str, variant: str) -> Path:
        return runs / f"{name}--{variant.replace(' ', '-')}.json"

    scenes = {scene.resolve().name: scene for scene in args.scenes}

    def wanted_settings(name: str, variant: str) -> dict:
        return settings_of(scene_key(scenes[name]), args.steps, args.seed, args.threads, args.points, args.device,
                           variant_overrides(args.overrides, variant))

    # A run is reused only if it was made with this call's settings: any other would stand in the table under this
    # command line. Checked for every run this call could reuse, before any runs.
    for name in scenes:
        for variant in [ALL] + [v for v in wanted if v not in DERIVED]:
            target = target_of(name, variant)
            if target.exists():
                try:
                    recorded = json.loads(target.read_text()).get("settings")
                except (OSError, ValueError, AttributeError):
                    recorded = None
                why = other_settings(recorded, wanted_settings(name, variant))
                if why:
                    parser.error(f"--out {args.out} holds a run made with other settings ({target.name}: {why}): "
                                 f"pass --overwrite to discard the earlier runs, or choose another --out")
    runs.mkdir(parents=True, exist_ok=True)
    captures = {}
    for name, scene in scenes.items():
        try:
            captures[name] = prepare_scene(scene.resolve(), args.out.resolve())
        except (OSError, SpadscanError) as exc:
            print(f"{parser.prog}: error: scene {scene}: cannot import it ({exc})", file=sys.stderr)
            return 1
    results: dict[str, dict[str, dict]] = {name: {} for name in captures}
    children = Children()

    def record(name: str, variant: str, res: dict) -> None:
        results[name][variant] = res
        # A successful all-parts run's report says which parts ran there, so which to ablate; it gives DERIVED's.
        if variant == ALL and not failed(res):
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
        res = run_in_child(captures[name], target, args, variant_overrides(args.overrides, variant),
                           scene_key(scenes[name]), children=children)
        if res is None:  # stopped (Ctrl-C): not run, "-"; the same command runs it again
            return
        if failed(res):
            print(f"  {name}, {variant}: failed: {res['failed']}", flush=True)
        else:
            print(f"  {name}, {variant}: {fmt(res.get('chamfer_mm'))} mm, {fmt(res.get('normal_error_deg'), 1)} deg, "
                  f"{res['steps']} steps ({time.perf_counter() - t0:.0f} s)", flush=True)
        record(name, variant, res)

    interrupted = False
    pool = ThreadPoolExecutor(args.jobs)
    # A time limit's SIGTERM ends the runs like Ctrl-C does: the table of the runs finished still comes out.
    before = signal.signal(signal.SIGTERM, signal.default_int_handler)
    # Ctrl-Z stops this script's process group, not the runs' own: passed on, it pauses them too.
    before_tstp = signal.signal(signal.SIGTSTP, lambda signum, frame: children.pause(signum))
    try:
        # Every scene's all-parts run first: its report says which parts ran there, so which to ablate.
        list(pool.map(lambda n: run(n, ALL), list(captures)))
        # Part by part across the scenes: an interrupted ablation leaves whole rows of the table.
        todo = [(name, v) for v in wanted for name in captures
                if v in results[name].get("_ran", []) and v not in results[name]]
        list(pool.map(lambda nv: run(*nv), todo))
    except KeyboardInterrupt:  # Ctrl-C: the runs queued are not started, those running are stopped (not failed)
        interrupted = True
        children.stop()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        signal.signal(signal.SIGTERM, before)
        signal.signal(signal.SIGTSTP, before_tstp)
    text = tables(results, [ALL] + wanted)
    (args.out / "table.md").write_text(text + "\n")
    write_atomic(args.out / "results.json", results)
    print(text)
    if interrupted:
        print(f"interrupted: the table holds the runs finished; the same command resumes from {runs}",
              file=sys.stderr)
        return 130
    gone = failures(results)
    if gone:
        print(f"{len(gone)} runs failed: {'; '.join(gone)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
