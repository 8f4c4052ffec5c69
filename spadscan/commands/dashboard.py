"""Serve a local web page that follows the lab's scans and reconstructions.

The page lists every scan under the captures root with its state and progress, shows the scan in hand (poses,
frame rate, its last histograms), the reconstruction queue (as `spadscan worker --status` lists it, with each
running job's progress), and each live or finished reconstruction's preview, 3D view and report. It updates itself
about once a second. The dashboard only reads the root (it changes no file) and asks the daemon for its status (see
below); it never talks to the arm itself.

At the top it says the daemon's state in the daemon's own words (`spadscan ctl status`: scanning, paused, idle; a
scan's scan.json says "running" while it is scanned) and, in one line, what the reconstruction side does: a worker at
its jobs, a job whose worker is gone, jobs or complete scans that no worker has taken for 20 s, a worker waiting for
scans, workers waiting for room on a full disk (where, how much is free, and that room must be made there: they take
no job until then), or no worker at all, with the command that starts a worker where one is wanted (a running worker,
idle or not, renews its file under QUEUE/workers/). That line stays one line (the middle of a long path gives way;
the whole line is its tooltip) so that nothing below it moves. The scan in hand, the reconstruction in view and its
3D view fit a 1280x800 window; a newer live view waits while the operator turns the shown one.

The 3D views are drawn by the browser (WebGL): the dashboard's machine needs no display and no off-screen OpenGL
(EGL or OSMesa). A result's mesh without a preview (a picture the worker draws off screen) says why as the result's
report does (the worker's machine could not draw off screen, a full disk), or else, where this dashboard's machine
cannot draw off screen, that, with what to install in its tooltip.

A scan left running by a daemon that is gone (crashed, killed or stopped: no process holds
CAPTURES/.spadscan-daemon.lock) is shown as "interrupted (no daemon running)", without a frame rate; a daemon
started on the root takes it over. The lock is seen where the daemon's flock is: on the daemon's machine, or over a
file system that shares flock locks between machines.

A scan whose scan.json says running but whose newest pose (or last scan.json write, a resume) is older than five
times its recent pose interval (the median gap between its last 8 poses), and never less than 120 s (the daemon's
default move timeout and a pose's frames), is shown as "stalled (no new pose for N s ...)", without a frame rate,
and the top line says "daemon: no new pose of SCAN for N s": the daemon may have paused without being able to record
it (a full disk) or be stuck; `spadscan ctl status` says which. Where the dashboard runs as the daemon's user, it
asks the daemon's control socket for its status as `spadscan ctl status` does (ctl's default socket, or --socket: a
rig config that sets `socket` needs its path given here), and the top line then says the daemon's state in its own
words (scanning, pausing, paused, idle, with the scan it holds), and a scan it could not take over as "not taken
over", with the daemon's reason and the way out (`spadscan ctl resume NAME` or `spadscan ctl abort NAME`). Where it
cannot ask (another user's daemon, another socket), the page says so in the top line's tooltip and tells the state
from the files as above. The daemon is asked at most once a second, however many pages are open, and only for its
status: that request moves nothing and starts or ends no scan, but it is `ctl status`'s own, and the daemon answers
it as it answers ctl: it reads the arm's speed slider afresh while no scan runs (paused or idle), counts a paused
scan's chunks in its folder, and, as at every request, writes again an abort that a full disk kept it from
recording.

It listens on 127.0.0.1 (this machine only) unless --host says otherwise, and serves nothing outside the root.
The root is the folder of scans, never one scan's own folder (that is refused, naming its parent); a root with no
scans yet, or none yet at all, is served all the same, saying so, and the page lists scans as they appear.
Ctrl-C or SIGTERM (`kill`, `systemctl stop`) stops it, saying so, with exit status 0.

examples:
  spadscan dashboard --root captures                  # then open http://127.0.0.1:8765/
  spadscan dashboard --root captures --port 9000
"""

from __future__ import annotations

import argparse
from pathlib import Path

from spadscan.daemon.root_lock import check_root_free
from spadscan.protocol.errors import ConfigError
from spadscan.signals import terminate_as_interrupt


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--root", type=Path, required=True, metavar="CAPTURES",
                        help="captures root: the folder whose sub-folders are scans (as the daemon and worker use)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on, IPv4 or IPv6 (default: 127.0.0.1, this machine only; ::1 the "
                             "same over IPv6; 0.0.0.0 opens it to the network)")
    parser.add_argument("--port", type=int, default=8765, help="port to listen on (default: 8765; 0: any free one)")
    parser.add_argument("--queue", type=Path, default=None, metavar="DIR",
                        help="the worker's queue folder (default: CAPTURES/.queue)")
    parser.add_argument("--socket", default=None, metavar="PATH",
                        help="the daemon's control socket, asked for the daemon's own state as `spadscan ctl status` "
                             "asks it (default: ctl's, $SPADSCAN_SOCKET or /tmp/spadscan-<uid>/spadscan.sock; the "
                             "rig config is not read: where it sets `socket`, give that path here)")


def daemon_running(root: Path) -> bool:
    """Whether a daemon may hold the captures root: the daemon's own read-only probe (`spadscan daemon --check`),
    handed to the dashboard, which does not import the daemon's package. A lock that cannot be read counts as held:
    in doubt, scans are shown as their scan.json says."""
    try:
        check_root_free(root)
    except ConfigError:
        return True
    return False


STATUS_TIMEOUT_S = 2.0
"""How long a poll waits for the daemon's status; one that does not answer by then is told from the files."""


def daemon_status(socket_path: str):
    """`daemon_status(root)` for the dashboard: the daemon's status reply over its control socket at `socket_path`
    (`spadscan ctl status`'s request; the client refuses a socket another user serves), or a ControlError why not."""

    def ask(root: Path) -> dict:
        from spadscan.daemon.client import call

        return call(socket_path, "status", STATUS_TIMEOUT_S)

    return ask


def run(args: argparse.Namespace) -> int:
    import sys

    from spadscan.dashboard.server import address, holds_no_scans, make_server

    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port} must be in [0, 65535]")
    from spadscan.daemon.client import default_socket_path

    socket_path = args.socket or default_socket_path(create=False)
    server = make_server(args.root, args.host, args.port, args.queue, daemon_running=daemon_running,
                         daemon_status=daemon_status(socket_path))
    print(f"spadscan dashboard: serving {args.root.resolve()} at {address(server)} (Ctrl-C stops it)",
          file=sys.stderr, flush=True)
    if not args.root.exists():  # served all the same: the daemon creates it at its first scan
        print(f"spadscan dashboard: the captures root {args.root} does not exist yet; the page waits for it (the "
              f"daemon creates it at its first scan)", file=sys.stderr, flush=True)
    elif holds_no_scans(args.root):  # served all the same: the daemon may start one any time
        print(f"spadscan dashboard: no scans in {args.root} yet (a scan is a sub-folder holding scan.json); the page "
              f"lists them as they appear", file=sys.stderr, flush=True)
    try:
        with terminate_as_interrupt():  # `systemctl stop` or `kill` stops it as Ctrl-C does, saying so
            server.serve_forever(poll_interval=0.25)
    except KeyboardInterrupt:
        # A service stopped as asked ends well (0), as the worker's does; the line tells the terminal it was heard.
        print("spadscan dashboard: stopped", file=sys.stderr, flush=True)
    finally:
        server.server_close()
    return 0
