"""Error against run time: every preset and baseline on every scene for the same wall-clock budget.

    python benchmarks/error_vs_time.py --scenes DIR... --budget-s S [--presets fast,paper] [--baselines]
                                       [--out FOLDER] [--overwrite] [--device auto|cpu|cuda] [--every-s 5]
                                       [--seed 0] [--marks 30,60,180] [--set KEY=VALUE ...]

A scene is a capture folder (holds scan.json) or a folder of the public dataset (holds <name>.json, imported once
into --out). Each preset runs in its own process (clean peak memory, nothing shared) through `spadscan reconstruct`'s
own set-up (`set_up_run`: the capture loaded, the preset's model built) and its training loop (`train`, with its
checkpoint scoring left out of the budget), with checkpoints every --every-s seconds of training that record the
Chamfer distance against the capture's ground truth. Run time is wall time from the start of loading the capture —
set-up (carving, ray tables) included — less the time spent evaluating checkpoints. On a real scene
with a table, Chamfer is measured on the object above the table: both meshes are cut 5 mm above the table top
(found in the ground truth as the largest horizontal face area). Baselines run once and are timed whole.

Prints one table (scene x method: Chamfer at each of --marks (default 30 s, 60 s, 180 s) and at the end, time to
reach 2 mm, peak memory of the method, its checkpoints' scoring left out), the speed-up of `fast` over `paper`
(time for `fast` to reach the Chamfer `paper` reaches at the end of its budget), and saves one plot
(error_vs_time.png) and all numbers (results.json) in --out. Every result records the commit of the code that made it
(with a note when the working tree held uncommitted changes) and its preset's resolved config.

A run writes its checkpoints so far to runs/<scene>-<method>.partial.json as it goes. If it is killed (Ctrl-C, or a
time limit's SIGTERM to this script), the table still comes out, with that run's checkpoints marked "cut off", and
the exit status is 130 (also where a run failed before). A run
whose own process fails (an error, or killed by another hand: the OOM killer's SIGKILL) is a failed run, not a cut-off
one: results.json records it with "failed" ("exit -9"), and its row reads "failed (exit -9)" with no final figure
(the checkpoints it left, if any, stay in the mark columns and the plot).

Every option is checked before the first run starts (presets, --set overrides against each preset, scene folders,
the device, --out); each problem is a one-line error and the exit status is 2. An --out that holds an earlier run
(runs/, results.json, table.md, error_vs_time.png) is refused unless --overwrite is given, which deletes that run's
files first (captures imported from the dataset, in captures/, are kept). A run that fails is named in one line and
the others go on; the exit status is then 1, after the table (the failed runs in it as failed).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path


MARKS_S = (30.0, 60.0, 180.0)
GOAL_MM = 2.0


# ---- scenes ---------------------------------------------------------------------------------------------------------
def dataset_file(path: Path) -> Path | None:
    """The dataset scene file (<name>.json) in a dataset folder, or None."""
    files = sorted(p for p in path.glob("*.json") if not p.name.endswith("_random.json"))
    return files[0] if files else None


def scene_problem(path: Path) -> str | None:
    """Why `path` cannot be a --scenes argument (one line), or None. Reads, never writes: a dataset folder is only
    imported once every option has been checked."""
    if not path.exists():
        return f"scene {path}: no such folder"
    if not path.is_dir():
        return f"scene {path}: not a folder (give a capture folder, or a dataset folder holding <name>.json)"
    if (path / "scan.json").is_file():
        return capture_problem(path)
    if dataset_file(path) is None:
        return f"scene {path}: holds neither scan.json (a capture) nor a dataset <name>.json"
    return None


def capture_problem(capture: Path) -> str | None:
    """Why the capture folder cannot be benchmarked (one line), or None: it must read, hold views, and any ground
    truth its manifest names must load (a capture that names none is run, without Chamfer figures)."""
    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.protocol.errors import SpadscanError
    from spadscan.worker.ground_truth import capture_ground_truth

    try:
        reader = CaptureReader(capture)
        if not reader.chunk_names():
            return f"scene {capture}: the capture holds no views"
    except (OSError, SpadscanError) as exc:
        return f"scene {capture}: {exc}"
    spec, why = capture_ground_truth(capture)  # the worker's: a scene placed with an offset has none to score by
    if spec is None and why is not None:
        return f"scene {capture}: its ground truth cannot be used ({why})"
    return None


def prepare_scene(path: Path, work: Path) -> Path:
    """A capture folder for a scene argument: the folder itself, or the dataset file inside it imported once into
    work/captures/<folder name> (imported again when the capture there came from another file)."""
    if (path / "scan.json").is_file():
        return path
    source = dataset_file(path)
    if source is None:
        raise SystemExit(f"error: {path} holds neither scan.json nor a dataset <name>.json")
    cap = work / "captures" / path.name
    if (cap / "scan.json").is_file() and imported_from(cap) != str(source.resolve()):
        if imported_from(cap) is None:  # not an import of this script's: somebody's capture, never deleted
            raise SystemExit(f"error: {cap} holds a capture that is no dataset import; move it, or choose another "
                             f"--out")
        import shutil

        shutil.rmtree(cap)
    if not (cap / "scan.json").is_file():
        from spadscan.protocol.lcspc import import_lcspc

        import_lcspc(source, cap)
    return cap


def imported_from(capture: Path) -> str | None:
    """The dataset file an imported capture was made from (its manifest's scene source), or None."""
    try:
        scene = json.loads((capture / "scan.json").read_text()).get("scene") or {}
        return scene.get("source") if isinstance(scene, dict) else None
    except (OSError, ValueError, AttributeError):
        return None


def ground_truth(capture: Path):
    """The capture's ground truth as a worker.ground_truth.GroundTruth (scored above a table slab it holds), or None
    when its scene record names none that loads (worker.ground_truth.capture_ground_truth: a dataset import's
    `ground_truth`, a simulated capture's `mesh` or `builtin` scene, none where the scene stood offset from it)."""
    from spadscan.worker.ground_truth import capture_ground_truth, load_ground_truth

    spec, _ = capture_ground_truth(capture)
    return load_ground_truth(spec) if spec else None


def chamfer_mm(mesh, truth, n_points: int) -> float | None:
    """Chamfer (mm) of `mesh` against a GroundTruth, or None where there is no surface to compare."""
    from spadscan.protocol.errors import SpadscanError

    try:
        return float(truth.metrics(mesh, n_points=n_points).chamfer_mm)
    except SpadscanError:
        return None


# ---- peak memory ----------------------------------------------------------------------------------------------------
class MethodPeak:
    """Peak memory of the method alone (MB): scoring a checkpoint (meshing, 300,000-point Chamfer) can take more
    memory than the method does, and would otherwise set the peak. The host's high-water mark (VmHWM) is read before
    each scoring and reset after it through /proc/self/clear_refs (Linux); a GPU's peak allocation likewise. Where the
    reset is not available the peak includes scoring, and `excludes_scoring` says so."""

    def __init__(self, device):
        self.device = device
        self.peak_kb = 0.0
        self.with_scoring_kb = 0.0  # the peak of the whole process (the reset clears ru_maxrss too)
        self.excludes_scoring = _reset_hwm()

    def pause(self) -> None:
        """Before scoring: take the method's high-water mark so far."""
        self.peak_kb = max(self.peak_kb, _hwm_kb())
        if self.device.type == "cuda":
            import torch

            self.peak_kb = max(self.peak_kb, torch.cuda.max_memory_allocated(self.device) / 1024)

    def resume(self) -> None:
        """After scoring: start the high-water marks afresh."""
        self.with_scoring_kb = max(self.with_scoring_kb, _hwm_kb())
        if self.excludes_scoring:
            self.excludes_scoring = _reset_hwm()
        if self.device.type == "cuda":
            import torch

            torch.cuda.reset_peak_memory_stats(self.device)

    def peak_mb(self) -> float:
        self.pause()
        return self.peak_kb / 1024

    def peak_with_scoring_mb(self) -> float:
        return max(self.with_scoring_kb, self.peak_kb, _hwm_kb()) / 1024


def _hwm_kb() -> float:
    """This process's peak resident memory (kB): VmHWM, which clear_refs resets, else ru_maxrss, which nothing does."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1])
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def _reset_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # 5: reset the peak resident set size to the current one
        return True
    except OSError:
        return False


# ---- one run (in its own process) -----------------------------------------------------------------------------------
def run_preset(capture: Path, preset: str, budget_s: float, every_s: float, device: str, seed: int,
               out: Path, eval_resolution: int | None = None, overrides: tuple[str, ...] | list[str] = (),
               partial: Path | None = None) -> dict:
    """Run one preset on one capture; returns {trace: [{seconds, wall_seconds, step, chamfer_mm}], ...}.
    With `partial`, the trace so far is rewritten there after every checkpoint, so that a run killed before its end
    (a time limit, Ctrl-C) still leaves its checkpoints behind."""
    import torch

    from spadscan.worker.recon.config import parse_override
    from spadscan.worker.recon.model_api import RunPlan
    from spadscan.worker.recon.trainer import train
    from spadscan.worker.reconstruct import resolve_device, run_config, set_up_run

    t0 = time.perf_counter()
    config = run_config(preset, dict(parse_override(text) for text in overrides))
    dev = resolve_device(device)
    truth = ground_truth(capture)
    meter = MethodPeak(dev)  # from here on: loading the ground truth is the benchmark's, not the method's
    # The model is laid out for the whole wall budget; it trains for what set-up leaves of it.
    run = set_up_run(capture, config, dev, steps=None, budget_s=budget_s, seed=seed, log=lambda line: None)
    setup_s, model = run.setup_s, run.model
    # Checkpoints are scored exactly like the final mesh (docs/metrics.md: 300,000 points, the full mesh resolution):
    # their time is not counted, and fewer points would raise the estimate's floor (~1.1 mm at 30,000 points).
    resolution = eval_resolution or config.mesh_resolution
    points = config.metrics_points

    def evaluate():
        meter.pause()
        try:
            mesh = model.extract_mesh(resolution)
            return {"chamfer_mm": chamfer_mm(mesh, truth, points)}
        except Exception as exc:  # no surface yet: the trace says so
            return {"chamfer_mm": None, "note": str(exc)}
        finally:
            meter.resume()

    provenance = {"commit": source_commit(), "config": config.to_dict()}
    keep = None if partial is None else partial_writer(partial, preset, str(dev), setup_s, provenance)
    plan = RunPlan(steps=None, budget_s=max(1.0, budget_s - setup_s), seed=seed)
    result = train(model, plan, every_s=every_s, evaluate=None if truth is None else evaluate,
                   scoring_in_budget=False, on_checkpoint=keep, progress=False, early_stop=config.early_stop)
    trace = with_wall_seconds(result.trace, setup_s)
    final = trace[-1].get("chamfer_mm")  # the last checkpoint is the end of the run
    peak_mb = meter.peak_mb()
    return {"method": preset, "kind": "preset", "device": str(dev),
            "device_name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor() or "cpu",
            "threads": torch.get_num_threads(), "setup_s": setup_s, "steps": result.steps,
            "train_s": result.seconds, "stopped_by": result.stopped_by, "overrides": list(overrides), "trace": trace,
            "final_chamfer_mm": final,
            "crop_z_m": None if truth is None else truth.cut_above_z_m, "peak_rss_mb": peak_mb,
            "peak_excludes_scoring": meter.excludes_scoring,
            "peak_rss_with_scoring_mb": meter.peak_with_scoring_mb(),
            "summary": _jsonable(model.summary()),
            "total_s": time.perf_counter() - t0, **provenance}


def source_commit() -> str:
    """The commit of the code being measured ('unknown' outside a git checkout), with ' + uncommitted changes' when
    the working tree differs from it."""
    git = ["git", "-C", str(Path(__file__).resolve().parents[1])]
    try:
        head = subprocess.check_output(git + ["rev-parse", "HEAD"], text=True, stderr=subprocess.DEVNULL, timeout=30)
        dirty = subprocess.check_output(git + ["status", "--porcelain", "--untracked-files=no"], text=True,
                                        stderr=subprocess.DEVNULL, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head.strip() + (" + uncommitted changes" if dirty.strip() else "")


def run_baseline(capture: Path, method: str, out: Path) -> dict:
    import resource

    from spadscan.worker.baselines.run import run_baseline as run
    import trimesh

    truth = ground_truth(capture)
    start = time.perf_counter()
    report = run(capture, out, method)
    seconds = time.perf_counter() - start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # before the scoring, as for the presets
    mesh = trimesh.load(out / "mesh.ply")
    c = chamfer_mm(mesh, truth, 300_000) if truth is not None else None
    return {"method": method, "kind": "baseline", "setup_s": 0.0, "trace": [{"wall_seconds": seconds,
            "chamfer_mm": c}], "final_chamfer_mm": c, "crop_z_m": None if truth is None else truth.cut_above_z_m,
            "threshold": report.get("threshold"),
            "peak_rss_mb": peak_mb, "commit": source_commit()}


def write_atomic(path: Path, record: dict) -> None:
    """Write JSON so that a reader (or a kill mid-write) never sees half a file."""
    from spadscan.protocol.atomic_files import write_atomic as replace_file

    replace_file(path, json.dumps(_jsonable(record), indent=1))


def _jsonable(obj):
    return json.loads(json.dumps(obj, default=lambda v: v.tolist() if hasattr(v, "tolist") else str(v)))


def partial_writer(path: Path, preset: str, device: str, setup_s: float, provenance: dict | None = None):
    """A checkpoint callback for the trainer (`on_checkpoint`) that rewrites `path` with the trace so far, as a
    'cut off' result; `provenance` (commit, config) goes with it."""
    def keep(trace_so_far: list[dict]) -> None:
        write_atomic(path, {"method": preset, "kind": "preset", "device": device, "setup_s": setup_s,
                            "stopped_by": "cut off", **(provenance or {}),
                            "trace": with_wall_seconds(trace_so_far, setup_s)})
    return keep


def with_wall_seconds(trace: list[dict], setup_s: float) -> list[dict]:
    """Checkpoints with their wall time: training seconds plus the set-up that came before them."""
    return [{**e, "wall_seconds": e["seconds"] + setup_s} for e in trace]


def partial_path(result: Path) -> Path:
    return result.with_name(result.stem + ".partial.json")


def failed_result(partial: Path, method: str, why: str) -> dict:
    """The result of a run whose process failed (`why`: 'exit -9'): the checkpoints it left, if any, with no final
    figure and `failed` saying how it ended; a failed run is never read as one that ran to its end or was cut off."""
    res = cut_off_result(partial) or {"method": method, "kind": "baseline" if method in BASELINES else "preset",
                                      "trace": []}
    return {**res, "failed": why, "stopped_by": "failed", "final_chamfer_mm": None, "peak_rss_mb": None}


def cut_off_result(partial: Path) -> dict | None:
    """The checkpoints a killed run left behind, as a result the table can show ('cut off'), or None if it left
    none with a Chamfer. Its final Chamfer is its last checkpoint's; its peak memory was not measured."""
    try:
        res = json.loads(partial.read_text())
    except (OSError, ValueError):
        return None
    if not res.get("trace"):
        return None
    res.update(final_chamfer_mm=res["trace"][-1].get("chamfer_mm"), peak_rss_mb=None)
    return res


# ---- tables and plot ------------------------------------------------------------------------------------------------
def chamfer_at(trace: list[dict], t: float) -> float | None:
    """The Chamfer of the last checkpoint at or before wall time t (None if none yet or no surface)."""
    best = None
    for e in trace:
        if e["wall_seconds"] <= t + 1e-9:
            best = e.get("chamfer_mm")
    return best


def time_to(trace: list[dict], goal: float) -> float | None:
    for e in trace:
        c = e.get("chamfer_mm")
        if c is not None and c <= goal:
            return e["wall_seconds"]
    return None


def ended(result: dict) -> str:
    """How a run ended: 'budget', where an early stop ended it ('converged 142 s') or where it was killed ('cut off
    142 s': its partial trace); 'failed (exit 1)' where its process failed; baselines run to the end."""
    if result.get("failed"):
        return f"failed ({result['failed']})"
    if result.get("stopped_by") in ("converged", "cut off"):
        return f"{result['stopped_by']} {result['trace'][-1]['wall_seconds']:.0f} s"
    return "budget" if result.get("kind") == "preset" else "done"


def fmt(v, unit="") -> str:
    return "-" if v is None else f"{v:.2f}{unit}"


def fmt_mb(v) -> str:
    return "-" if v is None else f"{v:.0f}"


def mark_value(result: dict, mark_s: float, budget_s: float) -> float | None:
    """The Chamfer a table shows at wall time mark_s. A run's last checkpoint is its budget's end, however far the
    last step overran it; a run that was cut off or failed has no figure after its last checkpoint."""
    if result.get("failed") or result.get("stopped_by") == "cut off":
        trace = result.get("trace") or []
        return chamfer_at(trace, mark_s) if trace and mark_s <= trace[-1]["wall_seconds"] else None
    if mark_s >= budget_s - 1e-9:
        return result.get("final_chamfer_mm")
    return chamfer_at(result["trace"], mark_s)


def table(results: list[dict], budget_s: float, marks_s=MARKS_S) -> str:
    """A markdown table, one row per result. The figure columns carry their unit in the header: Chamfer in mm at each
    mark and at the end ('mm @30 s', 'final mm'), wall time in s ('to 2 mm': its cells read '18.00 s'), peak memory
    in MB. Marks after the budget are left out."""
    marks = shown_marks(marks_s, budget_s)
    head = (["scene", "method"] + [f"mm @{m:g} s" for m in marks]
            + ["final mm", "ended", f"to {GOAL_MM:g} mm", "peak MB"])
    rows = [head]
    for r in results:
        final = r.get("final_chamfer_mm")
        rows.append([r["scene"], r["method"]] + [fmt(mark_value(r, m, budget_s)) for m in marks]
                    + [fmt(final), ended(r), fmt(time_to(r["trace"], GOAL_MM), " s"), fmt_mb(r.get("peak_rss_mb"))])
    widths = [max(len(row[i]) for row in rows) for i in range(len(head))]
    lines = ["| " + " | ".join(c.ljust(w) for c, w in zip(row, widths)) + " |" for row in rows]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)


def shown_marks(marks_s, budget_s: float) -> list[float]:
    """The marks that get a column: those at or before the budget."""
    return [m for m in marks_s if m <= budget_s + 1e-9]


def speedups(results: list[dict]) -> list[str]:
    out = []
    for scene in sorted({r["scene"] for r in results}):
        # A failed run's last checkpoint is not where its budget ended: no speed-up rests on it.
        by = {r["method"]: r for r in results if r["scene"] == scene and not r.get("failed")}
        if "fast" in by and "paper" in by:
            paper = [e for e in by["paper"]["trace"] if e.get("chamfer_mm") is not None]
            if not paper:
                continue
            target, t_paper = paper[-1]["chamfer_mm"], paper[-1]["wall_seconds"]
            t_fast = time_to(by["fast"]["trace"], target)
            ratio = "not reached" if t_fast is None else f"{t_paper / t_fast:.0f}x"
            out.append(f"{scene}: paper reaches {target:.2f} mm at {t_paper:.0f} s; fast reaches it at "
                       f"{fmt(t_fast, ' s')}: speed-up {ratio}")
    return out


def plotted(results: list[dict]) -> dict[str, list[tuple[dict, list]]]:
    """scene -> [(result, [(wall seconds, Chamfer mm)])] for the results that have a Chamfer to plot."""
    by_scene: dict[str, list[tuple[dict, list]]] = {}
    for r in results:
        pts = [(e["wall_seconds"], e["chamfer_mm"]) for e in r.get("trace", []) if e.get("chamfer_mm") is not None]
        if pts:
            by_scene.setdefault(r["scene"], []).append((r, pts))
    return dict(sorted(by_scene.items()))


def plain_log_ticks(axis) -> None:
    """Tick labels of a log axis as plain numbers ('20', '3', '0.5'), not '2x10^1'; which ticks get a label stays
    matplotlib's choice (the minor ticks' labels only where the axis spans little more than a decade)."""
    from matplotlib.ticker import LogFormatter

    class Plain(LogFormatter):
        def __call__(self, x, pos=None):
            return super().__call__(x, pos) and f"{x:g}"  # '' where matplotlib leaves a tick unlabelled

    axis.set_major_formatter(Plain(base=10))
    axis.set_minor_formatter(Plain(base=10, labelOnlyBase=False))


def figure(results: list[dict]):
    """The error-against-time figure (one panel per scene with a Chamfer to plot), or None when no result has one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by_scene = plotted(results)
    if not by_scene:
        return None
    fig, axes = plt.subplots(1, len(by_scene), figsize=(4.5 * len(by_scene), 3.6), squeeze=False)
    for ax, (scene, runs) in zip(axes[0], by_scene.items()):
        for r, pts in runs:
            t, c = zip(*pts)
            label = r["method"] + (f" (failed: {r['failed']})" if r.get("failed") else "")
            if r["kind"] == "baseline":
                ax.plot(t, c, "s", label=label)
            else:
                ax.plot(t, c, "-o", ms=2, label=label)
        ax.axhline(GOAL_MM, color="gray", ls=":", lw=1)
        ax.set_xscale("log")
        ax.set_yscale("log")
        plain_log_ticks(ax.xaxis)
        plain_log_ticks(ax.yaxis)
        ax.set_title(scene)
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel("Chamfer (mm)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def plot(results: list[dict], path: Path) -> bool:
    """Save the figure to `path`; False (nothing written) when no result has a Chamfer to plot."""
    fig = figure(results)
    if fig is None:
        return False
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


# ---- driver -----------------------------------------------------------------------------------------------------
def machine() -> str:
    import torch

    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = f", GPU {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"{cpu}, {os.cpu_count()} cores, torch {torch.__version__} ({torch.get_num_threads()} threads){gpu}; "
            f"load average {load:.1f} at start")


def parse_marks(text: str) -> tuple[float, ...]:
    """'5,10,30' -> (5.0, 10.0, 30.0): positive, finite, increasing seconds."""
    try:
        marks = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of seconds") from None
    if not marks or any(not (0 < m < float("inf")) for m in marks) or list(marks) != sorted(set(marks)):
        raise argparse.ArgumentTypeError(f"{text!r}: marks must be positive, finite and increasing")
    return marks


BASELINES = ("space-carving", "reprojection")
EARLIER_RUN = ("runs", "results.json", "table.md", "error_vs_time.png")
"""What a run leaves in --out (besides captures/, the dataset imports it reuses)."""


def presets_of(text: str) -> list[str]:
    """'fast, paper' -> ['fast', 'paper'] ('' -> [])."""
    return [p.strip() for p in text.split(",") if p.strip()]


def check_options(args) -> list[str]:
    """Every problem with the options, one line each ([] when the runs can start). Reads, never writes."""
    from spadscan.protocol.errors import SpadscanError
    from spadscan.protocol.folders import folder_problem
    from spadscan.worker.recon.config import parse_override, with_overrides
    from spadscan.worker.recon.presets import PRESETS, preset_config
    from spadscan.worker.reconstruct import resolve_device

    problems = []
    presets = presets_of(args.presets)
    if not presets and not args.baselines:
        problems.append("nothing to run: --presets is empty and --baselines is not given")
    seen = set()
    configs = {}
    for name in presets:
        if name in seen:
            problems.append(f"--presets: {name!r} is named twice")
            continue
        seen.add(name)
        if name in BASELINES:
            problems.append(f"--presets: {name!r} is a baseline, not a preset (known presets: {', '.join(PRESETS)}); "
                            "--baselines runs the baselines")
            continue
        try:
            configs[name] = preset_config(name)
        except SpadscanError as exc:
            configs.pop(name, None)
            problems.append(f"--presets: {exc}")
    overrides = {}
    for text in args.overrides:
        try:
            key, value = parse_override(text)
            overrides[key] = value
        except SpadscanError as exc:
            problems.append(f"--set: {exc}")
    if args.overrides and not presets:
        problems.append("--set changes the presets' configs, and no preset is run (--presets is empty)")
    for name, config in configs.items():
        try:
            with_overrides(config, overrides)
        except SpadscanError as exc:
            problems.append(f"--set: preset {name!r}: {exc}")
    try:
        resolve_device(args.device)
    except SpadscanError as exc:
        problems.append(f"--device: {exc}")
    names: dict[str, Path] = {}
    for scene in args.scenes:
        why = scene_problem(scene)
        if why:
            problems.append(why)
            continue
        name = scene.resolve().name
        if name in names and names[name].resolve() == scene.resolve():
            problems.append(f"scene {scene} is named twice")
        elif name in names:
            problems.append(f"scenes {names[name]} and {scene} share the name {name!r} (their runs would share "
                            f"runs/{name}-METHOD.json)")
        names[name] = scene
    out = args.out
    if out.exists() and not out.is_dir():
        problems.append(f"--out {out}: exists and is not a folder")
    elif (unmakeable := folder_problem(out)) is not None:
        problems.append(f"--out {out}: {unmakeable}")
    elif not args.overwrite:
        held = earlier_run(out)
        if held:
            problems.append(f"--out {out}: already holds an earlier run ({', '.join(held)}); choose another --out, "
                            "or pass --overwrite to replace it")
    return problems


def earlier_run(out: Path) -> list[str]:
    """The files and folders of an earlier run that `out` holds (runs/ only when it holds something)."""
    held = []
    for name in EARLIER_RUN:
        p = out / name
        if p.is_dir() and any(p.iterdir()) or p.exists() and not p.is_dir():
            held.append(name + "/" if p.is_dir() else name)
    return held


def clear_earlier_run(out: Path) -> list[str]:
    """Delete what an earlier run left in `out` (EARLIER_RUN); returns what was there."""
    import shutil

    held = earlier_run(out)
    for name in EARLIER_RUN:
        p = out / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
    return held


def run_all(args, captures: list[Path], methods: list[str], results: list[dict], failed: list[str]) -> None:
    """Each method on each capture, each in its own process; appends to `results` as runs end, and the runs that
    failed to `failed` ('sphere fast (exit 1)'). A run that fails is a result marked failed (`failed_result`); a run
    cut off by Ctrl-C or SIGTERM to this script contributes the checkpoints it left behind (its partial file), if
    any."""
    for capture in captures:
        for method in methods:
            result = args.out / "runs" / f"{capture.name}-{method}.json"
            result.parent.mkdir(parents=True, exist_ok=True)
            print(f"{capture.name}: {method} ...", file=sys.stderr, flush=True)
            cmd = [sys.executable, __file__, "--scenes", str(capture), "--budget-s", str(args.budget_s),
                   "--every-s", str(args.every_s), "--device", args.device, "--seed", str(args.seed)]
            cmd += ["--eval-resolution", str(args.eval_resolution)] if args.eval_resolution else []
            cmd += [x for kv in args.overrides for x in ("--set", kv)]
            cmd += ["--one", str(capture), method, str(result)]
            result.unlink(missing_ok=True)
            try:
                proc = subprocess.run(cmd)
            except KeyboardInterrupt:  # Ctrl-C or SIGTERM to this script: the run in progress counts as far as it got
                res = cut_off_result(partial_path(result))
                if res is not None:
                    results.append({**res, "scene": capture.name})
                raise
            # Ended by itself: finished, or failed (an error, or killed by another hand, as the OOM killer does).
            if proc.returncode == 0 and result.is_file():
                res = json.loads(result.read_text())
            else:
                why = f"exit {proc.returncode}" if proc.returncode else "exit 0 without a result"
                print(f"{capture.name}: {method} failed ({why})", file=sys.stderr)
                failed.append(f"{capture.name} {method} ({why})")
                res = failed_result(partial_path(result), method, why)
            results.append({**res, "scene": capture.name})


class Parser(argparse.ArgumentParser):
    """Usage errors in one line (the usage itself is in --help)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (0 < value < float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r} must be a positive, finite number of seconds")
    return value


def int_at_least(low: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < low:
            raise argparse.ArgumentTypeError(f"{text!r} must be an integer >= {low}")
        return value
    return parse


def main(argv=None) -> int:
    ap = Parser(prog=Path(__file__).name, description=__doc__.split("\n\n")[0],
                formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scenes", nargs="+", required=True, type=Path, metavar="DIR",
                    help="capture folders, or dataset folders holding <name>.json (imported into --out)")
    ap.add_argument("--budget-s", type=positive_seconds, required=True, help="wall-clock seconds per preset and scene")
    ap.add_argument("--presets", default="fast", help="comma-separated presets (default: fast; '' with --baselines: "
                                                      "the baselines alone)")
    ap.add_argument("--baselines", action="store_true", help="also run space carving and reprojection")
    ap.add_argument("--out", type=Path, default=Path("benchmark-out"),
                    help="output folder (default: benchmark-out, in the current folder)")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace the earlier run in --out: its runs/, results.json, table.md and error_vs_time.png\n"
                         "are deleted before the first run (without it, an --out holding any of them is refused;\n"
                         "captures/ imported from the dataset are kept and reused)")
    ap.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                    help="where every run trains: auto (CUDA when torch sees a GPU, else the CPU), cpu or cuda\n"
                         "(default: auto)")
    ap.add_argument("--every-s", type=positive_seconds, default=5.0,
                    help="seconds between checkpoints (default: 5)")
    ap.add_argument("--seed", type=int_at_least(0), default=0,
                    help="seed of every run, the same for each preset and scene (default: 0)")
    ap.add_argument("--marks", type=parse_marks, default=MARKS_S, metavar="S,S,...",
                    help="wall times (s) of the table's Chamfer columns (default: 30,60,180; on a GPU, where the goal "
                         "is 2 mm in 10 s, e.g. 5,10,30;\nmarks after --budget-s get no column)")
    ap.add_argument("--eval-resolution", type=int_at_least(2), default=None, metavar="N",
                    help="marching-cubes cells along the longest side for every checkpoint (default: each preset's "
                         "mesh resolution; an MLP's 256^3 evaluation takes minutes on a CPU: 128 keeps paper runs "
                         "short, at about a millimetre of added error)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                    help="override a field of every preset's config, as `spadscan reconstruct --set` does "
                         "(repeatable; checked against every preset before the first run)")
    ap.add_argument("--one", nargs=3, metavar=("CAPTURE", "METHOD", "RESULT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:  # child process: one method on one capture
        return run_one(args)

    from spadscan.protocol.errors import SpadscanError

    problems = check_options(args)
    for line in problems:
        print(f"{ap.prog}: error: {line}", file=sys.stderr)
    if problems:
        return 2
    dropped = [m for m in args.marks if m not in shown_marks(args.marks, args.budget_s)]
    if dropped:
        print(f"note: marks {', '.join(f'{m:g}' for m in dropped)} s come after the {args.budget_s:g} s budget: "
              "no column for them", file=sys.stderr)
    if args.overwrite:
        held = clear_earlier_run(args.out)
        if held:
            print(f"--overwrite: deleted the earlier run's {', '.join(held)} in {args.out}", file=sys.stderr)
    args.out.mkdir(parents=True, exist_ok=True)
    captures = []
    for scene_dir in args.scenes:
        try:
            capture = prepare_scene(scene_dir.resolve(), args.out.resolve())
        except (OSError, SpadscanError) as exc:
            print(f"{ap.prog}: error: scene {scene_dir}: cannot import it ({exc})", file=sys.stderr)
            return 1
        why = capture_problem(capture) if capture != scene_dir.resolve() else None  # an import, checked now
        if why:
            print(f"{ap.prog}: error: {why}", file=sys.stderr)
            return 1
        captures.append(capture)
    methods = presets_of(args.presets) + (list(BASELINES) if args.baselines else [])
    header, commit = machine(), source_commit()
    print(f"machine: {header}; commit {commit}", file=sys.stderr)
    results, failed = [], []
    interrupted = False
    # A time limit's SIGTERM ends the runs like Ctrl-C does: the table still comes out.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        run_all(args, captures, methods, results, failed)
    except KeyboardInterrupt:  # Ctrl-C: the table of the runs so far, the one in progress as far as it got
        interrupted = True
        print("interrupted: the table holds the runs so far", file=sys.stderr)
    text = [f"Machine: {header}", f"Commit: {commit}", f"Budget: {args.budget_s:g} s wall per run (set-up included)"]
    text += [f"Overrides: {' '.join(args.overrides)}"] if args.overrides else []
    text += ["", table(results, args.budget_s, args.marks), ""] + speedups(results)
    print("\n".join(text))
    (args.out / "results.json").write_text(json.dumps({"machine": header, "commit": commit, "budget_s": args.budget_s,
                                                       "results": results}, indent=1))
    (args.out / "table.md").write_text("\n".join(text) + "\n")
    if plot(results, args.out / "error_vs_time.png"):
        print(f"plot: {args.out / 'error_vs_time.png'}", file=sys.stderr)
    elif failed and len(failed) == len(captures) * len(methods):
        print("no plot: every run failed", file=sys.stderr)
    elif not results:
        print("no plot: no run finished", file=sys.stderr)
    else:
        print("no plot: no run has a Chamfer (its capture names no ground truth)", file=sys.stderr)
    if failed:
        print(f"{len(failed)} of {len(captures) * len(methods)} runs failed: {', '.join(failed)}", file=sys.stderr)
    if interrupted:  # a script or a time limit that waits on it tells a cut-off table from a whole one
        return 130
    return 1 if failed else 0


def run_one(args) -> int:
    """The child process: one method on one capture, its result written to RESULT. A problem is one line on stderr
    (exit 1): the parent names the run that failed."""
    from spadscan.protocol.errors import SpadscanError

    capture, method, result = Path(args.one[0]), args.one[1], Path(args.one[2])
    out = result.parent / (result.stem + "-files")
    try:
        if method in BASELINES:
            res = run_baseline(capture, method, out)
        else:
            res = run_preset(capture, method, args.budget_s, args.every_s, args.device, args.seed, out,
                             args.eval_resolution, args.overrides, partial_path(result))
    except KeyboardInterrupt:  # the parent reads the partial file
        return 130
    except SpadscanError as exc:
        print(f"error: {capture.name}: {method}: {exc}", file=sys.stderr)
        return 1
    write_atomic(result, res)
    partial_path(result).unlink(missing_ok=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
