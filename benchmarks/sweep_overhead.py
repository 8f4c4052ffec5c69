"""What Dask costs a sweep: the small example's wall time on 1 and 2 workers, and the overhead of a point that does
nothing, side by side with running the same points one after the other in one process.

    python benchmarks/sweep_overhead.py [--sweep examples/sweeps/small.toml] [--noop-points 200] [--workers 1,2]

Every run starts from an empty results folder under --out (default: a temporary folder). The serial column calls
`run_point` in a loop in this process (one torch thread, as on a worker); the Dask columns run `spadscan sweep`'s
runner on a LocalCluster of that many worker processes, one thread each. The no-op points go through the whole
machinery (submission, scheduling, a point file written atomically, the events, results.csv) but compute nothing:
their time per point is the scheduler's and the runner's overhead. Wall times depend on what else the machine runs:
the load average at the start is printed with them.
"""

from __future__ import annotations

import argparse
import tomllib
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from spadscan.sweep.plan import make_plan
from spadscan.sweep.point import run_point
from spadscan.sweep.runner import cores, run_sweep
from spadscan.sweep.spec import load_spec, parse_spec
from spadscan.sweep.store import SweepDir

REPO = Path(__file__).resolve().parents[1]


def noop_point(task, out, device, keep):
    """A point that does nothing but record itself, as a real point does (pickled by value onto the workers)."""
    from spadscan.sweep.store import SweepDir

    SweepDir(out).write_point({"id": task.id, "status": "done", "reason": None, "scene": task.scene.label,
                               "params": task.params, "methods": {}})
    return {"id": task.id, "status": "done", "reason": None}


def noop_plan(n: int, folder: Path):
    """A plan of `n` distinct points (seeds 0..n-1 of a tiny condition)."""
    path = folder / "noop.toml"
    text = (f'[sweep]\nscenes = ["builtin:sphere"]\n[base]\nviews = 4\n[grid]\nseed = {list(range(n))}\n')
    path.write_text(text)
    return make_plan(parse_spec(tomllib.loads(text), path, text))


def serial(plan, out: Path, point) -> float:
    """Wall seconds to run every point of `plan` one after the other in this process."""
    store = SweepDir(out)
    store.open(plan)
    start = time.perf_counter()
    try:
        for task in plan.points.values():
            point(task, str(out.resolve()))
        store.write_results(plan)
    finally:
        store.close()
    return time.perf_counter() - start


def on_dask(plan, out: Path, workers: int, point=None) -> tuple[float, float, int]:
    """(wall seconds, of which cluster start-up, failed points) of the sweep runner on a LocalCluster."""
    start = time.perf_counter()
    extra = {} if point is None else {"point": point}
    summary = run_sweep(plan, out, workers=workers, progress=False, **extra)
    return time.perf_counter() - start, summary.startup_s, len(summary.failed)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sweep", default=str(REPO / "examples" / "sweeps" / "small.toml"),
                    help="the sweep whose wall time is measured (default: examples/sweeps/small.toml)")
    ap.add_argument("--noop-points", type=int, default=200, help="points that do nothing (default: 200)")
    ap.add_argument("--workers", default="1,2", help="worker counts of the Dask columns (default: 1,2)")
    ap.add_argument("--skip-sweep", action="store_true", help="measure the no-op points alone")
    ap.add_argument("--out", default=None, help="folder for the results (default: a temporary one, removed)")
    args = ap.parse_args(argv)
    workers = [int(w) for w in args.workers.split(",") if w.strip()]
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="sweep-overhead-"))
    root.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0]
    print(f"machine: {cores()} cores, load average {load:.1f} at the start; python {sys.version.split()[0]}")
    rows = []
    try:
        if not args.skip_sweep:
            plan = make_plan(load_spec(args.sweep))
            print(f"{args.sweep}: {len(plan.points)} points", flush=True)

            def real_point(task, out):
                return run_point(task, out)

            row = {"what": f"{Path(args.sweep).name}: {len(plan.points)} points, wall s",
                   "serial": serial(plan, root / "sweep-serial", real_point)}
            start_row = {"what": "  of which cluster start-up, s", "serial": None}
            for w in workers:
                wall, startup, failed = on_dask(plan, root / f"sweep-dask-{w}", w)
                row[w], start_row[w] = wall, startup
                if failed:
                    print(f"warning: {failed} points failed on {w} workers", flush=True)
            rows += [row, start_row]
        plan = noop_plan(args.noop_points, root)
        n = len(plan.points)
        row = {"what": f"{n} no-op points: ms per point",
               "serial": 1e3 * serial(plan, root / "noop-serial", lambda t, o: noop_point(t, o, "cpu", False)) / n}
        start_row = {"what": "  cluster start-up, s (not in the above)", "serial": None}
        for w in workers:
            wall, startup, _ = on_dask(plan, root / f"noop-dask-{w}", w, noop_point)
            row[w], start_row[w] = 1e3 * (wall - startup) / n, startup
        rows += [row, start_row]
    finally:
        if args.out is None:
            shutil.rmtree(root, ignore_errors=True)
    head = ["", "serial, 1 process"] + [f"dask, {w} worker{'' if w == 1 else 's'}" for w in workers]
    print()
    print("| " + " | ".join(head) + " |")
    print("|" + "|".join("---" for _ in head) + "|")
    for r in rows:
        cells = [r["what"]] + ["-" if r.get(k) is None else f"{r[k]:.1f}" for k in ["serial", *workers]]
        print("| " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
