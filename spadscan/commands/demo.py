"""Run the whole loop on simulated devices and print where the results are.

Starts the acquisition daemon (simulated arm, or the real ur_rtde client against a simulated UR controller with
--arm ur-sim) with a simulated sensor rendering a built-in scene, scans it through the control socket, lets a worker
process reconstruct the capture, and ends with a summary: the mesh, the pictures, the HTML report, the Chamfer
distance against the scene's ground truth and the time each stage took (also in OUT/summary.json).
Every process it starts is stopped again, also on Ctrl-C.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("spadscan-demo"), metavar="DIR",
                        help="folder for config, captures, logs and summary.json (default: ./spadscan-demo)")
    parser.add_argument("--scene", default="demo",
                        help="built-in scene: demo (goblet: a bowl and a thin stem), cup, lamp, sphere, pyramid "
                             "(default: demo)")
    parser.add_argument("--views", type=int, default=128,
                        help="sensor poses in the scan (default: 128; with 64 the goblet's fit is coarser and "
                             "varies more from seed to seed)")
    parser.add_argument("--budget-s", type=float, default=120.0, metavar="S",
                        help="training seconds of the reconstruction, as `spadscan reconstruct --budget-s` "
                             "(default: 120)")
    parser.add_argument("--arm", choices=("sim", "ur-sim"), default="sim",
                        help="sim: simulated arm; ur-sim: the real ur_rtde client against a simulated UR "
                             "controller on loopback (default: sim)")
    parser.add_argument("--sensor", choices=("lcspc-sim", "tmf8820"), default="lcspc-sim",
                        help="simulated sensor model (default: lcspc-sim)")


def run(args: argparse.Namespace) -> int:
    import sys

    from tqdm import tqdm

    from spadscan.demo import DemoOptions, check_options, run_demo

    opts = DemoOptions(out=args.out, scene=args.scene, views=args.views, budget_s=args.budget_s, arm=args.arm,
                       sensor=args.sensor)
    check_options(opts)  # before the banner: a refused option starts nothing and announces nothing

    def bar(total: int, desc: str):
        return tqdm(total=total, desc=desc, unit="pose", file=sys.stderr, leave=True)

    print(f"spadscan demo: scene {opts.scene}, {opts.views} views, {opts.arm} arm, {opts.sensor} sensor, "
          f"reconstruction budget {opts.budget_s:g} s; logs in {opts.out / 'logs'}", file=sys.stderr)
    s = run_demo(opts, bar)
    chamfer = s["chamfer_mm"]
    secs = s["seconds"]
    print(f"mesh:     {s['mesh']}")
    print(f"report:   {s['report_html']}  ({s['report']})")
    print(f"pictures: {', '.join(s['pictures']) or '-'}")
    print(f"chamfer:  {'n/a' if chamfer is None else f'{chamfer:.2f} mm'} against the scene's ground truth "
          f"(preset {s['preset']})")
    print(f"time:     start {secs['start_s']:.1f} s, scan {secs['scan_s']:.1f} s, reconstruction "
          f"{secs['reconstruct_s']:.1f} s, total {secs['total_s']:.1f} s")
    print(f"summary:  {opts.out / 'summary.json'}")
    return 0
