"""Steps per second of the default `spadscan reconstruct` on an idle machine and beside CPU-bound competitors.

    python benchmarks/contention.py [--capture CAPTURE] [--budget-s 30] [--busy 0,1,2]

A lab PC runs the daemon, a browser and a worker at once: the reconstruction's default thread count must not make a
step many times slower when other processes want the cores. This runs `spadscan reconstruct` exactly as a user
would (no --threads, and OMP_NUM_THREADS / MKL_NUM_THREADS removed from its environment, so that its own default
decides) with a whole-run budget of --budget-s seconds (set-up, mesh and pictures included; the table's "train s"
is the training part of it), first alone, then beside one and two competing processes that spin on one core each.
The benchmark starts the competitors, waits until each one spins, and stops them when the run ends; each also stops
by itself after a deadline or once the benchmark is gone, and the run is started to stop with the benchmark too, so
none outlives it, even killed. The early stop is switched off (--set early_stop=false) so that every run trains for
as much of the budget as it can. Ctrl-C (or SIGTERM) prints the rows measured so far.

Prints, side by side: steps, training seconds, steps per second, the ratio to the idle rate and the goal (>= 0.7x
beside one competitor, >= 0.4x beside two). The capture defaults to the built-in cup simulated like the public
dataset (lcspc-sim, 256 views). Other load on the machine skews every figure: the load average before each run is
printed with it.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

from spadscan import parent_watch
from spadscan.protocol.child_command import module_command

GOALS = {1: 0.7, 2: 0.4}
"""Competitors -> the least fraction of the idle step rate that the default must keep."""

SPIN = """
import os, sys, time
deadline, parent = time.monotonic() + float(sys.argv[1]), int(sys.argv[2])
print("spinning", flush=True)
x = 0
try:
    # A benchmark killed outright (SIGKILL) cannot stop us, and leaves us to init: getppid() changes. Looked at once
    # in 65536 turns, so that the spin stays a spin.
    while time.monotonic() < deadline and (x & 0xFFFF or os.getppid() == parent):
        x += 1
except KeyboardInterrupt:  # Ctrl-C reaches the whole group: the benchmark says what was stopped, not each of us
    pass
"""


def start_competitors(n: int, deadline_s: float) -> list[subprocess.Popen]:
    """n processes that each spin on one core until `deadline_s` seconds pass, this process is gone or they are
    stopped; returns once every one has said it spins."""
    procs = [subprocess.Popen([sys.executable, "-c", SPIN, str(deadline_s), str(os.getpid())],
                              stdout=subprocess.PIPE, text=True)
             for _ in range(n)]
    try:
        for p in procs:
            if p.stdout.readline().strip() != "spinning":
                raise RuntimeError(f"a competing process exited before it spun (status {p.wait()})")
    except BaseException:
        stop(procs)
        raise
    return procs


def stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
        if p.stdout is not None:
            p.stdout.close()


def default_env() -> dict:
    """This process's environment without the thread-count variables the default would otherwise obey, naming this
    process as the parent to stop with (spadscan/parent_watch.py): a killed benchmark leaves no run behind."""
    env = parent_watch.child_env()
    for key in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.pop(key, None)
    return env


def run_reconstruct(capture: Path, out: Path, budget_s: float) -> dict:
    """One `spadscan reconstruct` run as a user starts it; its report.json."""
    cmd = module_command("spadscan.cli", "reconstruct", capture, "--out", out, "--budget-s", f"{budget_s:g}",
                         "--no-gt", "--no-progress", "--set", "early_stop=false")
    done = subprocess.run(cmd, env=default_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if done.returncode != 0:
        last = done.stderr.strip().splitlines()[-1:] or [f"exit status {done.returncode}"]
        raise SystemExit(f"contention.py: error: `spadscan reconstruct {capture}` failed: {last[0]}")
    return json.loads((out / "report.json").read_text())


def make_capture(folder: Path) -> Path:
    capture = folder / "cup"
    cmd = module_command("spadscan.cli", "simulate", "builtin:cup", "--out", capture,
                         "--sensor", "lcspc-sim", "--views", "256", "--seed", "0", "--no-progress")
    done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                          env=parent_watch.child_env())
    if done.returncode != 0:
        last = done.stderr.strip().splitlines()[-1:] or [f"exit status {done.returncode}"]
        raise SystemExit(f"contention.py: error: simulating the built-in cup failed: {last[0]}")
    return capture


def table(rows: list[tuple], args) -> str:
    """The rows measured, each beside the idle one (the first) and its goal."""
    idle = rows[0][4]
    lines = [f"default `spadscan reconstruct` on {args.capture or 'the built-in cup (lcspc-sim, 256 views)'}, "
             f"{args.budget_s:g} s budget per run (the whole run), {os.cpu_count()} cores",
             f"{'competing processes':>20} {'threads':>8} {'load before':>12} {'steps':>7} {'train s':>8} "
             f"{'steps/s':>8} {'x idle':>7} {'goal':>8}"]
    for n, load, steps, seconds, rate, threads in rows:
        goal = GOALS.get(n)
        verdict = "" if goal is None else (f">= {goal:.1f}x " + ("met" if rate / idle >= goal else "MISSED"))
        lines.append(f"{n:>20} {threads!s:>8} {load:>12.2f} {steps:>7} {seconds:>8.1f} {rate:>8.2f} "
                     f"{rate / idle:>7.2f} {verdict:>8}")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capture", type=Path, default=None,
                        help="capture folder to reconstruct (default: the built-in cup, simulated into a temporary "
                             "folder)")
    parser.add_argument("--budget-s", type=float, default=30.0,
                        help="whole-run budget of each `spadscan reconstruct` (set-up, mesh and pictures included; "
                             "the table's 'train s' is the training part; default: 30)")
    parser.add_argument("--busy", default="0,1,2", help="competing processes of each run (default: 0,1,2; 0 "
                                                          "is the idle run every ratio refers to)")
    args = parser.parse_args(argv)
    try:
        counts = [int(v) for v in args.busy.split(",")]
    except ValueError:
        parser.error(f"--busy {args.busy!r}: comma-separated whole numbers")
    if not counts or counts[0] != 0 or any(c < 0 for c in counts):
        parser.error(f"--busy {args.busy!r} must start with 0 (the idle run) and hold no negative count")
    if not args.budget_s > 0:
        parser.error(f"--budget-s {args.budget_s} must be > 0")
    if args.capture is not None and not (args.capture / "scan.json").is_file():
        parser.error(f"--capture {args.capture}: no capture there (no scan.json)")

    # A time limit's SIGTERM ends the runs like Ctrl-C does: the `finally`s below stop the competitors and the run
    # and remove the temporary folder (on SIGTERM's default, nothing would), and the rows so far still come out.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    work = Path(tempfile.mkdtemp(prefix="contention-"))
    rows = []
    try:
        capture = args.capture or make_capture(work)
        for n in counts:
            load = os.getloadavg()[0]
            procs = start_competitors(n, deadline_s=4 * args.budget_s + 300)
            try:
                report = run_reconstruct(capture, work / f"run-{n}", args.budget_s)
            finally:
                stop(procs)
            rate = report["steps"] / report["seconds"] if report["seconds"] else float("nan")
            rows.append((n, load, report["steps"], report["seconds"], rate, report.get("torch_threads")))
            print(f"  {n} competing: {report['steps']} steps in {report['seconds']:.1f} s "
                  f"(load average before: {load:.2f})", file=sys.stderr, flush=True)
    except KeyboardInterrupt:
        print(f"interrupted: {len(rows)} of {len(counts)} runs measured", file=sys.stderr, flush=True)
        if rows:
            print(table(rows, args))
        return 130
    finally:
        shutil.rmtree(work, ignore_errors=True)

    print(table(rows, args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
