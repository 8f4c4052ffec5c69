"""Run the simulated UR controller as a process: `python -m spadscan.daemon.ursim --host 127.0.0.N`.

Prints one line once it listens, then serves until SIGINT or SIGTERM. With `--control-stdio` it also takes JSON-line
requests (fault injection, recorded moves) on stdin and stops when stdin closes; see `remote.py`.
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys

from spadscan.daemon.ursim.remote import serve_stdio
from spadscan.daemon.ursim.sim_controller import SimURController
from spadscan.parent_watch import watch_parent_from_env
from spadscan.protocol.errors import SpadscanError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m spadscan.daemon.ursim", description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.1", help="loopback address to listen on (default 127.0.0.1)")
    parser.add_argument("--time-scale", type=float, default=1.0,
                        help="multiply every motion time by this (0 = moves finish at once; default 1)")
    parser.add_argument("--speed-slider", type=float, default=1.0,
                        help="the pendant's speed slider: moves run at this fraction of their speed (0 < f <= 1)")
    parser.add_argument("--pose-noise-m", type=float, default=0.0,
                        help="standard deviation of the reported actual TCP position, per axis (m; default 0)")
    parser.add_argument("--tcp-offset", default="0,0,0,0,0,0", metavar="X,Y,Z,RX,RY,RZ",
                        help="the pendant's active TCP offset in the flange frame [m, rad] that get_tcp_offset "
                             "answers (default 0,0,0,0,0,0: the bare flange; the UR arm backend refuses any other)")
    parser.add_argument("--control-stdio", action="store_true",
                        help="take JSON-line requests on stdin, answer on stdout; stop when stdin closes")
    args = parser.parse_args(argv)
    watch_parent_from_env()  # started by `spadscan demo`: stop when the demo is gone
    try:
        controller = SimURController(args.host, time_scale=args.time_scale)
        controller.configure(speed_slider=args.speed_slider, pose_noise_m=args.pose_noise_m,
                             tcp_offset=args.tcp_offset.split(","))
    except SpadscanError as exc:
        print(f"ursim: error: {exc}", file=sys.stderr)
        return 1

    def ready() -> None:
        print(f"ursim listening on {args.host} (RTDE 30004, dashboard 29999, script 30003)", flush=True)

    async def run() -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, controller.request_stop)
        await controller.serve(ready)

    try:
        if args.control_stdio:
            return _serve_with_stdio(controller, ready)
        asyncio.run(run())
    except OSError as exc:
        print(f"ursim: error: cannot listen on {args.host}: {exc}", file=sys.stderr)
        return 1
    return 0


def _serve_with_stdio(controller: SimURController, ready) -> int:
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        controller.start()
    except SpadscanError as exc:
        print(f"ursim: error: {exc}", file=sys.stderr)
        return 1
    try:
        ready()
        serve_stdio(controller)
    finally:
        controller.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
