"""Serve a local web page that follows the lab's scans and reconstructions.

The page lists every scan under the captures root with its state and progress, shows the scan in hand (poses,
frame rate, its last histograms), the reconstruction queue (as `spadscan worker --status` lists it, with each
running job's progress), and each live or finished reconstruction's preview, 3D view and report. It updates itself
about once a second. The dashboard only reads the root: it never talks to the arm or changes a file.

It listens on 127.0.0.1 (this machine only) unless --host says otherwise, and serves nothing outside the root.

examples:
  spadscan dashboard --root captures                  # then open http://127.0.0.1:8765/
  spadscan dashboard --root captures --port 9000
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--root", type=Path, required=True, metavar="CAPTURES",
                        help="captures root: the folder whose sub-folders are scans (as the daemon and worker use)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (default: 127.0.0.1, this machine only; 0.0.0.0 opens it to "
                             "the network)")
    parser.add_argument("--port", type=int, default=8765, help="port to listen on (default: 8765; 0: any free one)")
    parser.add_argument("--queue", type=Path, default=None, metavar="DIR",
                        help="the worker's queue folder (default: CAPTURES/.queue)")


def run(args: argparse.Namespace) -> int:
    import sys

    from spadscan.dashboard.server import address, make_server
    from spadscan.protocol.errors import ConfigError

    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port} must be in [0, 65535]")
    server = make_server(args.root, args.host, args.port, args.queue)
    print(f"spadscan dashboard: serving {args.root.resolve()} at {address(server)} (Ctrl-C stops it)",
          file=sys.stderr, flush=True)
    try:
        server.serve_forever(poll_interval=0.25)
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0
