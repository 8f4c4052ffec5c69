"""Run the whole loop on simulated devices and print where the results are.

Starts the acquisition daemon (simulated arm, or the real ur_rtde client against a simulated UR controller with
--arm ur-sim) with a simulated sensor rendering a built-in scene, scans it through the control socket, lets a worker
process reconstruct the capture, and ends with a summary: the mesh, the pictures, the HTML report (with a 3D view
to turn), the Chamfer distance against the scene's ground truth and the time each stage took (also in
OUT/summary.json). The worker reconstructs live by default (`spadscan worker --live`): it starts on the scan's first
chunk, the scan's progress bar shows the live fit (views used of those published, steps, Chamfer) and a line is
printed each time its state changes; once the scan is complete the final reconstruction continues from the live
fit for --budget-s seconds. --offline reconstructs only once the scan is complete, as `spadscan worker --once`.
While the final reconstruction runs, a progress line shows its training time, loss and Chamfer; when the worker
runs the job again (its process crashed), the line starts over, named after the attempt, and a line says why the
last attempt ended.
The bars are drawn on a terminal; with standard error in a file or a pipe (`2>demo.log`, nohup) each bar is plain
lines instead, one at each tenth of it and at least every 30 s, and one at its end with its last reading (--progress
draws the bars there too; --no-progress shows neither, and the other lines and the summary still come).
With --dashboard it also serves the lab dashboard on its captures and prints the address to open.
Every process it starts is stopped again, also on Ctrl-C. Run again into the same --out after a run was stopped
during its scan, it aborts the scan that run left unfinished (its poses stay on disk, the capture marked aborted),
says so, and starts a new one; an unfinished scan there that no demo run started (OUT/demo-scans.txt lists those
that did) is left alone, and the demo stops naming it. After a run was stopped during its reconstruction, its scan
(complete, not reconstructed) is reconstructed first, before the new scan: one line names it, it has a bar of its
own, a line gives its report, and its time stays out of the new scan's reconstruction time and summary (Ctrl-C
meanwhile keeps it queued, for the next run or `spadscan worker --root OUT/captures --once`).
The demo writes its own rig config, OUT/rig.toml, anew on each run: an OUT that holds a rig.toml no demo run wrote (a
lab rig's own) is refused, as is an OUT that is a capture or lies inside one, or a lab's captures root (it holds a
daemon's .spadscan-daemon.lock or a worker's .queue); all before anything starts.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from spadscan.cli import add_progress_options, progress_bar_wanted


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("spadscan-demo"), metavar="DIR",
                        help="folder for config (rig.toml, written anew on each run), captures, logs and "
                             "summary.json (default: ./spadscan-demo); refused: a capture, a lab's captures root, or a "
                             "folder that holds a rig.toml the demo did not write")
    parser.add_argument("--scene", default="demo",
                        help="built-in scene: demo (goblet: a bowl and a thin stem), cup, lamp, sphere, pyramid, or "
                             "any other `spadscan simulate --help` lists (default: demo)")
    parser.add_argument("--views", type=int, default=128,
                        help="sensor poses in the scan (default: 128; with 64 the goblet's fit is coarser and "
                             "varies more from seed to seed)")
    parser.add_argument("--budget-s", type=float, default=120.0, metavar="S",
                        help="seconds of the whole reconstruction job, from its start to its report, as "
                             "`spadscan worker --budget-s`; live, of the final run that continues from the live fit "
                             "once the scan is complete (default: 120)")
    parser.add_argument("--offline", action="store_true",
                        help="reconstruct only once the scan is complete (`spadscan worker --once`) instead of "
                             "live while it runs")
    parser.add_argument("--arm", choices=("sim", "ur-sim"), default="sim",
                        help="sim: simulated arm; ur-sim: the real ur_rtde client against a simulated UR "
                             "controller on loopback (default: sim)")
    parser.add_argument("--sensor", choices=("lcspc-sim", "tmf8820"), default="lcspc-sim",
                        help="simulated sensor model (default: lcspc-sim)")
    parser.add_argument("--dashboard", action="store_true",
                        help="serve the lab dashboard (`spadscan dashboard`) on the demo's captures while it runs, "
                             "and print its address")
    parser.add_argument("--dashboard-port", type=int, default=8765, metavar="PORT",
                        help="the dashboard's port on 127.0.0.1 (default: 8765; a free one when it is busy)")
    add_progress_options(parser, "draw no progress bars and write no progress lines (the lines that say what "
                                 "happens, and the summary, still come)",
                         "a plain line at each tenth of a bar and at least every 30 s, and its last reading at its "
                         "end", bars=True)


def run(args: argparse.Namespace) -> int:
    import sys

    from tqdm import tqdm

    from spadscan.demo import DemoOptions, check_options, make_out, run_demo

    opts = DemoOptions(out=args.out, scene=args.scene, views=args.views, budget_s=args.budget_s, arm=args.arm,
                       sensor=args.sensor, dashboard=args.dashboard, dashboard_port=args.dashboard_port,
                       live=not args.offline)
    check_options(opts)  # before the banner: a refused option starts nothing and announces nothing
    make_out(opts)  # so is an --out that cannot be written: the banner names its logs folder

    bar = progress_factory(args)

    def say(line: str) -> None:
        # Above the bar in front, not glued to its end: tqdm clears the bar, prints the line and draws the bar again.
        tqdm.write(line, file=sys.stderr)

    print(f"spadscan demo: scene {opts.scene}, {opts.views} views, {opts.arm} arm, {opts.sensor} sensor, "
          f"{'live reconstruction, final run' if opts.live else 'reconstruction'} budget {opts.budget_s:g} s; "
          f"logs in {opts.out / 'logs'}", file=sys.stderr)
    s = run_demo(opts, bar, say)
    chamfer = s["chamfer_mm"]
    secs = s["seconds"]
    print(f"mesh:     {s['mesh']}")
    for warning in s["warnings"]:  # as report.json says them (what ended a run that did not converge too)
        print(f"warning:  {warning}")
    print(f"pictures: {', '.join(s['pictures']) or '-'}")
    if s["live"] is not None:
        start = ("the final run continued from them" if s["live"].get("final_start", "live") == "live" else
                 "the final run started from the carved hull (the live fit was too young to go on from)")
        print(f"live:     {s['live'].get('views_used')} views and {s['live'].get('steps')} steps fitted while the "
              f"scan ran; {start}")
    print(f"chamfer:  {'n/a' if chamfer is None else f'{chamfer:.2f} mm'} against the scene's ground truth "
          f"(preset {s['preset']})")
    after = "reconstruction after the scan" if s["live"] is not None else "reconstruction"
    print(f"time:     start {secs['start_s']:.1f} s, scan {secs['scan_s']:.1f} s, {after} "
          f"{secs['reconstruct_s']:.1f} s, total {secs['total_s']:.1f} s")
    if s.get("earlier"):
        print(f"earlier:  {', '.join(e['scan'] for e in s['earlier'])}, left complete but not reconstructed, "
              f"took {secs['earlier_s']:.1f} s before this run's scan (not in the times above)")
    print(f"summary:  {opts.out / 'summary.json'}")
    if s["dashboard"]:
        print(f"dashboard: stopped; to look again: spadscan dashboard --root {opts.out / 'captures'}")
    print(f"report:   {s['report_html']}  (open it in a browser: the 3D view, the pictures and the numbers)")
    return 0


def progress_factory(args: argparse.Namespace):
    """What run_demo makes its bars with, progress_factory(total, desc, unit): a tqdm bar on a terminal (or with
    --progress); in a file or a pipe, which would keep every frame a bar redraws, plain lines (ProgressLines: a line at
    each tenth and every 30 s, the end's once; seconds said as training's and checkpoint scoring's, which a demo's
    job counts in its budget: its scenes have a ground truth); with --no-progress a bar that shows nothing."""
    import sys
    import time

    from tqdm import tqdm

    from spadscan.worker.recon.trainer import SCORING_COUNTED, ProgressLines

    drawn = progress_bar_wanted(args)

    def bar(total: float, desc: str, unit: str):
        if drawn:
            return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=True,
                        bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} " + unit + " [{elapsed}<{remaining}{postfix}]")
        if args.no_progress:
            return tqdm(total=total, desc=desc, unit=unit, disable=True)  # every call a bar takes, nothing shown
        return ProgressLines(total, desc, unit, time.monotonic, sys.stderr,
                             what=SCORING_COUNTED if unit == "s" else None)

    return bar
