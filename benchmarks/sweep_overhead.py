"""What Dask costs a sweep: the small example's wall time on 1 and 2 workers, and the overhead of a point that does
nothing, side by side with running the same points one after the other in one process.

    python benchmarks/sweep_overhead.py [--sweep examples/sweeps/small.toml] [--noop-points 200] [--workers 1,2]

Every run starts from an empty results folder under --out (default: a temporary folder). The serial column calls
`run_point` in a loop in this process (one torch thread, as on a worker); the Dask columns run `spadscan sweep`'s
runner on a LocalCluster of that many worker processes, one thread each. The no-op points go through the whole
machinery (submission, scheduling, a point file written atomically, the events, results.csv) but compute nothing:
their time per point is the scheduler's and the runner's overhead, from the cluster's start to its close; the
cluster's start-up and its shutdown (the client's and the cluster's close) are each a row of their own. Wall times
depend on what else the machine runs: the load average at the start is printed with them.
"""

from __future__ import annotations

import argparse
import contextlib
import tomllib
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from spadscan.protocol.errors import SpadscanError
from spadscan.sweep import runner
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


@contextlib.contextmanager
def timed_close():
    """Sums the seconds spent closing the runner's client and LocalCluster inside the block (yields a one-item list).
    run_sweep's summary holds the start-up alone; the close (a second or more, whatever the points) is no per-point
    overhead, and the serial peer has none."""
    seconds = [0.0]
    close = runner._client.__exit__

    def timed(self, *exc):
        t0 = time.perf_counter()
        try:
            return close(self, *exc)
        finally:
            seconds[0] += time.perf_counter() - t0

    runner._client.__exit__ = timed
    try:
        yield seconds
    finally:
        runner._client.__exit__ = close


def on_dask(plan, out: Path, workers: int, point=None) -> tuple[float, float, float, int]:
    """(wall seconds, of which cluster start-up, of which cluster shutdown, failed points) of the sweep runner on a
    LocalCluster."""
    extra = {} if point is None else {"point": point}
    with timed_close() as shutdown:
        start = time.perf_counter()
        summary = run_sweep(plan, out, workers=workers, progress=False, **extra)
        wall = time.perf_counter() - start
    return wall, summary.startup_s, shutdown[0], len(summary.failed)


def worker_counts(text: str) -> list[int]:
    """--workers: comma-separated counts, each >= 1."""
    try:
        counts = [int(w) for w in text.split(",") if w.strip()]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be comma-separated worker counts, each >= 1")
    return counts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sweep", default=str(REPO / "examples" / "sweeps" / "small.toml"),
                    help="the sweep whose wall time is measured (default: examples/sweeps/small.toml)")
    ap.add_argument("--noop-points", type=int, default=200, help="points that do nothing (default: 200)")
    ap.add_argument("--workers", type=worker_counts, default=[1, 2],
                    help="worker counts of the Dask columns (default: 1,2)")
    ap.add_argument("--skip-sweep", action="store_true", help="measure the no-op points alone")
    ap.add_argument("--out", default=None, help="folder for the results (default: a temporary one, removed)")
    args = ap.parse_args(argv)
    workers = args.workers
    if args.noop_points < 1:
        ap.error(f"--noop-points {args.noop_points} must be >= 1")
    sweep_plan = None
    if not args.skip_sweep:
        try:  # checked before anything runs
            sweep_plan = make_plan(load_spec(args.sweep))
        except SpadscanError as exc:
            ap.error(f"--sweep: {exc}")
    try:
        return measure(args, workers, sweep_plan)
    except SpadscanError as exc:  # a cluster that would not start, say
        raise SystemExit(f"{ap.prog}: error: {exc}") from None


def measure(args, workers: list[int], plan) -> int:
    """Every row (the sweep's when `plan` is given, then the no-op points'), then the table."""
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="sweep-overhead-"))
    root.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0]
    print(f"machine: {cores()} cores, load average {load:.1f} at the start; python {sys.version.split()[0]}")
    rows = []
    try:
        if plan is not None:
            print(f"{args.sweep}: {len(plan.points)} points", flush=True)

            def real_point(task, out):
                return run_point(task, out)

            row = {"what": f"{Path(args.sweep).name}: {len(plan.points)} points, wall s",
                   "serial": serial(plan, root / "sweep-serial", real_point)}
            start_row = {"what": "  of which cluster start-up, s", "serial": None}
            close_row = {"what": "  of which cluster shutdown, s", "serial": None}
            for w in workers:
                wall, startup, shutdown, failed = on_dask(plan, root / f"sweep-dask-{w}", w)
                row[w], start_row[w], close_row[w] = wall, startup, shutdown
                if failed:
                    print(f"warning: {failed} points failed on {w} workers", flush=True)
            rows += [row, start_row, close_row]
        plan = noop_plan(args.noop_points, root)
        n = len(plan.points)
        row = {"what": f"{n} no-op points: ms per point",
               "serial": 1e3 * serial(plan, root / "noop-serial", lambda t, o: noop_point(t, o, "cpu", False)) / n}
        start_row = {"what": "  cluster start-up, s (not in the above)", "serial": None}
        close_row = {"what": "  cluster shutdown, s (not in the above)", "serial": None}
        for w in workers:
            wall, startup, shutdown, _ = on_dask(plan, root / f"noop-dask-{w}", w, noop_point)
            row[w], start_row[w], close_row[w] = 1e3 * (wall - startup - shutdown) / n, startup, shutdown
        rows += [row, start_row, close_row]
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
