"""Run a sensitivity sweep: simulate -> reconstruct -> baselines -> metrics at every point of a grid, on Dask.

SWEEP.toml names the scenes (mesh files, builtin:NAME, or lcspc:NAME with --lcspc), the base condition (sensor
preset, schedule, views, bins, field of view, power, ambient light, laser cycles, seed) and the values of each
parameter to vary: one axis at a time around the base (the paper's design) or every combination (mode = "product").
At each point the capture is simulated, each preset reconstructs it, both baselines run with their threshold
calibrated against the ground truth, and everything is scored (see examples/sweeps/ for commented files).

Points run on Dask distributed: an embedded cluster of --workers processes (default: one per core), one thread each,
or the workers of a running scheduler (--scheduler tcp://HOST:8786; the machines must share DIR and the scenes'
files). Results survive: each finished point is written at once to DIR/points/<id>.json and gathered into
DIR/results.csv; a re-run of the same sweep runs only the points not done (failed ones again, each only its methods
not done) and the stale ones, stored by another spadscan version or --device or before a preset's or a baseline's
defaults changed (said in one line; a stale result stays until its new one is stored); a point whose worker
dies runs again on another (one that kills every worker it is tried on fails, saying how the last one ended where
the embedded cluster knows it: the signal, as "killed (SIGKILL: out of memory, or killed by hand?)" or "crashed
(SIGSEGV)", or the exit code, or "stopped by Dask for using too much memory" where it passed 95% of its memory limit,
an equal share of the machine's memory per worker); a sweep file whose base condition or methods differ from those DIR
was run with is refused, and so is one whose grid lacks entries DIR holds results of (a grown grid is welcome;
--overwrite runs it, and results.csv then holds its entries alone). Failed points are results too: they are listed at
the end and marked in `spadscan sweep-plot DIR`; the exit status is 0 once every point has run. A scheduler lost
mid-sweep (stopped, its machine gone) ends the run with one line and exit status 1, recording nothing for the points
it was waiting for (a stored result stays as it was): the same command runs them. A result whose run
warned (a preset that did not converge; any method's report.json warnings) is counted at the end, carried into
results.csv (<method>_converged, <method>_warning_count, <method>_warnings: the lines joined by " | ") and marked in
the plot; so is a baseline whose calibrated threshold is at an end of those tried (<method>_threshold_edge). Without
[grid], the sweep runs the base condition alone.

Progress: a bar on standard error where it is a terminal; in a file or a pipe (nohup, a batch job, `2>sweep.log`) a
line per finished point instead, as with --no-progress (--progress draws the bar there too).

Examples:
  spadscan sweep examples/sweeps/small.toml --out sweep-small && spadscan sweep-plot sweep-small
  spadscan sweep examples/sweeps/figure_a.toml --out figure-a --lcspc ~/data/LCSPCData --scheduler tcp://head:8786
"""

from __future__ import annotations

import argparse
import sys

from spadscan.cli import add_progress_options, progress_bar_wanted


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("sweep", metavar="SWEEP.toml", help="the sweep file")
    parser.add_argument("--out", required=True, metavar="DIR", help="results folder (created, or re-run into)")
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="a running Dask scheduler (tcp://host:8786); default: start a local cluster")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="worker processes of the local cluster (default: one per CPU core; with --device "
                             "cuda, or auto on a machine with a GPU, one)")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda", "auto"),
                        help="where the presets reconstruct (default: cpu; auto: the local cluster's machine's GPU "
                             "where torch sees one, else its CPU; on a scheduler each worker's own); cuda points go "
                             "only to workers started with --resources GPU=1 (without --scheduler, cuda is refused "
                             "where torch sees no CUDA device; points stored with another device run their presets "
                             "again)")
    parser.add_argument("--lcspc", default=None, metavar="DIR",
                        help="the LCSPCData folder (the one holding simulated/) for lcspc:NAME scenes")
    parser.add_argument("--keep", action="store_true",
                        help="keep each point's capture and outputs in DIR/work/<id>/ (default: removed)")
    parser.add_argument("--overwrite", action="store_true",
                        help="run a sweep file whose grid lacks entries DIR holds results of: results.csv, "
                             "sweep.json and sweep.toml become this file's (the other points' results stay in "
                             "DIR/points/, and a run of their own file gathers them again)")
    parser.add_argument("--dry-run", action="store_true",
                        help="check the file and list the points and how many are done (and stale: they would run "
                             "again); run nothing")
    add_progress_options(parser, "no progress bar: a line on standard error per finished point instead (its id, "
                                 "status, Chamfer per method and warnings), for a log",
                         "a line per finished point, as with --no-progress")


def run(args) -> int:
    from pathlib import Path

    from spadscan.protocol.folders import check_folder_option
    from spadscan.sweep.checks import check_scheduler_address, check_workers, local_device
    from spadscan.sweep.plan import make_plan
    from spadscan.sweep.spec import load_spec

    def log(line: str) -> None:
        print(f"spadscan sweep: {line}", file=sys.stderr, flush=True)

    # Refused before anything runs (the dry run too: what the run would refuse, it refuses).
    check_workers(args.scheduler, args.workers)
    device = args.device
    if args.scheduler is not None:
        check_scheduler_address(args.scheduler)
    else:
        device = local_device(device)
    spec = load_spec(args.sweep)
    plan = make_plan(spec, None if args.lcspc is None else Path(args.lcspc))
    # --out before the plan's line: a folder the run cannot make or write into is refused in one line naming it
    # (not an OS error about its lock file after the plan was announced); the dry run too, as the run would.
    check_folder_option(args.out, "--out")
    log(f"{counted(len(plan.entries), 'grid entry', 'grid entries')} on {counted(len(plan.scenes), 'scene')}: "
        f"{counted(len(plan.points), 'distinct point')}; methods {', '.join(spec.methods)}"
        + ("" if spec.grid else " (no [grid]: the base condition alone)"))
    if args.dry_run:
        return _dry_run(plan, Path(args.out), args.overwrite, device)
    from spadscan.signals import terminate_as_interrupt
    from spadscan.sweep.runner import run_sweep

    # SIGTERM as Ctrl-C: the local cluster's worker processes are stopped, not left running without a client.
    try:
        with terminate_as_interrupt():
            summary = run_sweep(plan, Path(args.out), scheduler=args.scheduler, workers=args.workers,
                                device=device, keep=args.keep, progress=progress_bar_wanted(args), log=log,
                                overwrite=args.overwrite)
    except KeyboardInterrupt:
        # Dask cannot stop a task that runs: a scheduler's workers finish the points they hold, and a re-run waits.
        running = ("; points already running on the scheduler's workers finish there first"
                   if args.scheduler is not None else "")
        print(f"spadscan sweep: interrupted; the points finished are kept in {args.out}, and the same command runs "
              f"the rest{running}", file=sys.stderr)
        return 130
    print("\n".join(finished_lines(summary, spec.base, Path(args.out), [p.name for p in spec.presets])))
    return 0


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """`n` and `noun`, plural unless `n` is 1 (`plural`, or `noun` + s)."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


def finished_lines(summary, base: dict, out, presets=()) -> list[str]:
    """What a finished run prints: the points run and done, each failed point, the points whose results warn or
    whose baselines' thresholds are at an end of those tried (`presets`: the methods that are presets), and where the
    results are."""
    return [f"{counted(summary.points, 'point')}: {summary.earlier} done earlier, {summary.ran} run now "
            f"({summary.done} done, {len(summary.failed)} failed)",
            *(f"  failed: {task.describe(base)} [{task.id}]: {reason}" for task, reason in summary.failed),
            *_ending_lines(summary, presets),
            f"results: {out / 'results.csv'} ({counted(summary.rows, 'row')}); plot: spadscan sweep-plot {out}"]


def _ending_lines(summary, presets) -> list[str]:
    """'3 of 12 points warn (fast 3): see results.csv's fast_converged, fast_warnings', and the like for the
    baselines' thresholds at an end of those tried; nothing where no point has either."""
    from spadscan.sweep.store import column_name

    lines = []
    warned = _per_method(getattr(summary, "warned", {}))
    if warned:
        columns = [c for m in warned for c in ((f"{column_name(m)}_converged",) if m in presets else ())
                   + (f"{column_name(m)}_warnings",)]
        n = len(summary.warned)
        lines.append(f"{n} of {counted(summary.points, 'point')} warn{'s' if n == 1 else ''} "
                     f"({', '.join(f'{m} {k}' for m, k in warned.items())}): see results.csv's {', '.join(columns)}")
    edge = _per_method(getattr(summary, "edge", {}))
    if edge:
        n = len(summary.edge)
        lines.append(f"{n} of {counted(summary.points, 'point')} ha{'s' if n == 1 else 've'} a baseline's threshold at "
                     f"the edge of the tried thresholds ({', '.join(f'{m} {k}' for m, k in edge.items())}): see "
                     f"results.csv's {', '.join(f'{column_name(m)}_threshold_edge' for m in edge)}; one beyond them "
                     f"may do better ([baselines] thresholds)")
    return lines


def _per_method(points: dict) -> dict:
    """{point: [methods]} -> {method: how many points}, in the order first met."""
    counts: dict[str, int] = {}
    for methods in points.values():
        for m in methods:
            counts[m] = counts.get(m, 0) + 1
    return counts


def _dry_run(plan, out, overwrite: bool = False, device: str = "cpu") -> int:
    from spadscan.sweep.fingerprint import Digests, Expected
    from spadscan.sweep.store import SweepDir

    store = SweepDir(out)
    store.check(plan, overwrite)  # what the run would refuse, the dry run refuses too
    done = stale = 0
    digests = Digests()
    for task in plan.points.values():
        result = store.read_point(task.id) if out.is_dir() else None
        # done, stale (done, to run again), failed or to run
        status = Expected(task, device, digests=digests).state(result)
        done += status == "done"
        stale += status == "stale"
        print(f"{task.id}  {status:<7} {task.describe(plan.spec.base)}")
    print(f"{counted(len(plan.points), 'point')}, {done} done, {len(plan.points) - done} to run"
          + (f" ({stale} stale)" if stale else ""))
    return 0
