"""Talk to a running daemon over its control socket (JSON lines).

    spadscan ctl status                         state, scan, pose i/n, frames, rate, time left, last error, sensor
                                                counters, and the scan's live reconstruction (`live`) when a worker
                                                runs one
    spadscan ctl scan --name bunny --views 128  start a scan; it is written to <captures>/bunny/
    spadscan ctl pause | resume | abort         pause after the poses under way, continue, or stop for good
    spadscan ctl resume NAME | abort NAME       take over and continue, or end as aborted (every chunk kept), an
                                                interrupted scan the daemon could not take over (`status` says why)
    spadscan ctl wait bunny                     block until the scan is complete (exit 0) or aborted (exit 1);
                                                on a terminal a progress bar (pose i/n) runs on stderr, otherwise
                                                a line on stderr says why whenever the scan pauses (and how its
                                                live reconstruction stands); Ctrl-C stops only the waiting, the
                                                scan goes on
    spadscan ctl shutdown                       stop the daemon (a scan in flight stays resumable)

`scan`, `pause`, `resume`, `abort` and `shutdown` answer in one line for people: the scan in hand, its state and its
pose i/n (`scan 'bunny' paused at pose 38/128: paused by user`; an abort, the pose the scan stopped at: `scan 'bunny'
aborted at pose 38/128`); with --json they print the daemon's whole reply as one line of JSON instead. `status` and
`wait` always print JSON; `status` takes --json too (then on one line), so that a script may pass it to every
operation, and so does `wait` (then its line is the daemon's status as
the scan ended, as `status --json` prints it, even when the daemon has started the next scan since, or the status it
answers then for a scan that ended before it started; with `wait`: the scan's name, how it ended (and why, where
that was said), how long the wait took; its progress stays on stderr). With --json a refusal, or no
daemon answering, is printed on standard output as {"ok": false, "error": ...} too, beside its error line on stderr
and exit status 1.

The live reconstruction (`spadscan worker --live`) is read from the scan's recon/live/status.json, beside the daemon:
views used of those published, steps, whether it converged, the Chamfer when the scene is known, the last update.
While its job waits in the worker's queue (<captures>/.queue), behind the jobs that take every job process the
workers run, `status` (`live`: `queued`) and `wait` say what it waits for, in the dashboard's words: `live
reconstruction queued: waiting for q1-fast to finish (the worker runs 1 job at a time; `--processes 2` runs 2)`.

Units: metres, seconds, degrees. The socket defaults to $SPADSCAN_SOCKET, else /tmp/spadscan-<uid>/spadscan.sock,
the daemon's default too (also as a systemd service); pass --socket to match the daemon's `socket` config key. ctl
talks only to a daemon that runs as the same user.
"""

from __future__ import annotations

import json
import math
import os
import stat
import sys
import time
from pathlib import Path

PROGRESS_POLL_S = 0.5  # how often `wait` asks for the status while its progress bar runs

# option -> ([scan] key, type); None values are left out so the daemon's [scan] defaults apply
SCAN_OPTIONS = {
    "views": ("views", int), "schedule": ("schedule", str), "rings": ("rings", int), "radius": ("radius_m", float),
    "target": ("target", None), "min_elevation": ("min_elevation_deg", float),
    "max_elevation": ("max_elevation_deg", float), "jitter": ("jitter_deg", float), "seed": ("seed", int),
    "order": ("order", str), "frames_per_pose": ("frames_per_pose", int), "settle": ("settle_s", float),
    "chunk_size": ("chunk_size", int), "initial_views": ("initial_views", int),
    "stop_when_converged": ("stop_when_converged", None),
}


MAX_TIMEOUT_S = 1e9
"""The longest --timeout, in seconds: more than any wait needs, well within what a socket's timeout takes."""


def _seconds(text: str) -> float:
    """argparse type of --timeout: a positive, finite number of seconds."""
    import argparse

    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of seconds")
    if value > MAX_TIMEOUT_S:  # the socket's timeout overflows the C time types above about 9.2e9 s
        raise argparse.ArgumentTypeError(f"{text!r} seconds is more than can be waited (at most {MAX_TIMEOUT_S:g} "
                                         f"s, about 31 years; `wait` and `scan --wait` wait for ever without "
                                         f"--timeout)")
    return value


def _socket(text: str) -> str:
    """argparse type of --socket: a path, never empty (an empty one would quietly mean the default socket)."""
    import argparse

    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path names no socket (leave --socket out for the default)")
    return text


def _target(text: str) -> list[float]:
    import argparse

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"{text!r} is not X,Y,Z in metres")
    return values


REPLY_TIMEOUT_S = {"scan": 600.0, "resume": 600.0}
"""Default seconds to wait for the reply of these operations (others: 30). Before the arm moves, the daemon asks the
arm's controller about every pose left (about 17 ms a pose on an e-Series, 38 on a CB-series): a plan of thousands
of views takes minutes, and a client that gave up first would report a scan that still starts as unanswered."""


def add_arguments(parser) -> None:
    from spadscan.daemon.client import default_socket_path

    import argparse

    def common(p, default):
        p.add_argument("--socket", type=_socket, default=default, metavar="PATH",
                       help=f"the daemon's control socket (default: {default_socket_path(create=False)})")
        p.add_argument("--timeout", type=_seconds, default=default, metavar="S",
                       help="seconds to wait for the reply, > 0 and at most 1e9 (default: 30; `scan` and `resume`: "
                            "600, since the arm's controller is first asked about every pose left, a minute or more "
                            "for thousands; `wait` and `scan --wait`: forever)")

    common(parser, None)
    shared = argparse.ArgumentParser(add_help=False)
    common(shared, argparse.SUPPRESS)  # also accepted after the operation: `ctl status --socket PATH`
    sub = parser.add_subparsers(dest="op", required=True, metavar="OP")

    def op(name: str, help_: str, description: str | None = None):
        return sub.add_parser(name, help=help_, description=description or help_, parents=[shared])

    status = op(
        "status", "print the daemon's state as JSON",
        "Print the daemon's state as JSON. `rate_hz`: frames published per second over the last 10 s (`rate_unit`: "
        "frames/s; a pose takes `frames_per_pose` of them), null while the scan is paused; `eta_s`: the seconds the "
        "scan has left at that pace (the poses still to take), null while paused or before a pace is measured; "
        "`elapsed_s`: seconds since this daemon started the scan or took it over, pauses included; "
        "`scan_elapsed_s`: seconds since the scan began (`started_utc`, its scan.json's created_utc), across daemon "
        "restarts, pauses and the time no daemon ran included (null when scan.json does not say); `last_error`: "
        "the last fault since the scan in hand (or the last one) started, or what still stands (an abort not "
        "recorded yet, a scan that could not be taken over); `live`: the scan's live reconstruction "
        "(recon/live/status.json) when a worker runs one (`spadscan worker --live`), with "
        "`age_s`, the seconds since its last update, and `queued` while its job waits in the worker's queue "
        "(<captures>/.queue; alone before the job's first status): `job`, `waiting_s`, `behind` (the jobs of other "
        "scans running now, one of which must end first when every job process is busy), `workers` (those present), "
        "`processes` (the jobs they run at once), `room_waits` (the workers that wait for room on a full disk "
        "before they claim again, each one's `room_wait` from its presence file: mount, folder, free_bytes, "
        "need_bytes, since_unix, retry_unix, quota) and `said`, what it waits for as the dashboard says it ('waiting "
        "for q1-fast to finish (the worker runs 1 job at a time; `--processes 2` runs 2)', 'a worker takes it at its "
        "next look', 'the worker waits for room on /data (12 MB free, 40 MB needed): make room there; it claims "
        "again by 2025-03-01 14:05 UTC (sooner once there is room)': once the first of the workers' own waits "
        "ends, and no sooner than the last wait of a job given back to the queue on a full disk, which holds every "
        "claim; or 'no worker is running: start one with ...'); "
        "`poses_to_take_again`: the poses missing from the capture (a damaged chunk moved out) that the scan takes "
        "again before it goes on; while the scan is paused, its progress (`pose`, `frames` and this list) is counted "
        "afresh from its folder as the resume will count it (a chunk moved out during the pause shows at once: the "
        "newest ones as a lower `pose` and `frames`, the scan going on from the first pose they held, any other "
        "under this list); `poses_to_take_again_note`: while paused, why that count is left to the resume and the "
        "progress is as last counted (a chunk changed since the daemon read it), the list then given even when "
        "empty; "
        "`speed_scaling` and `speed_note`: a UR arm's "
        "speed slider, when below 100 % (the scan runs that much slower), read afresh when status is asked while the "
        "scan is paused or the daemon idle; `speed_scaling_age_s`: seconds since it was read (the note says so when it "
        "could not be renewed for over 5 s).")
    scan = op("scan", "start a scan (options override the config's [scan] defaults)",
              "Start a scan. Every scan setting left out takes the daemon's default: the [scan] value of its rig "
              "config (examples/README.md documents each key).")
    scan.add_argument("--name", help="scan name: the capture goes to <captures>/NAME/; 1-100 letters, digits or "
                           ". _ + -, not starting with . _ + - (default: scan-<time>)")
    scan.add_argument("--wait", action="store_true",
                      help="block until the scan is complete or aborted (a progress bar on stderr when a terminal)")
    settings = scan.add_argument_group("scan settings", "each defaults to the rig config's [scan] key named in "
                                                        "brackets")
    settings.add_argument("--views", type=int, help="number of sensor poses [views]")
    settings.add_argument("--schedule", choices=("fibonacci", "rings", "adaptive"),
                          help="pose layout; adaptive: views ranked by a live reconstruction, else a Fibonacci "
                               "plan [schedule]")
    settings.add_argument("--rings", type=int,
                          help="elevation rings; schedule 'rings' only, views must be a multiple [rings]")
    settings.add_argument("--radius", type=float, metavar="M", help="sensor-to-target distance (m) [radius_m]")
    settings.add_argument("--target", type=_target, metavar="X,Y,Z",
                          help="point every view looks at, base frame (m) [target]")
    settings.add_argument("--min-elevation", type=float, metavar="DEG",
                          help="lowest view elevation (degrees) [min_elevation_deg]")
    settings.add_argument("--max-elevation", type=float, metavar="DEG",
                          help="highest view elevation (degrees) [max_elevation_deg]")
    settings.add_argument("--jitter", type=float, metavar="DEG",
                          help="largest random tilt off the target (degrees) [jitter_deg]")
    settings.add_argument("--seed", type=int, help="random seed of the jitter [seed]")
    settings.add_argument("--order", choices=("nearest", "serpentine", "planned"), help="visiting order [order]")
    settings.add_argument("--frames-per-pose", type=int, metavar="K",
                          help="frames stored per pose, never summed [frames_per_pose]")
    settings.add_argument("--settle", type=float, metavar="S",
                          help="wait after each move before frames count (s) [settle_s]")
    settings.add_argument("--chunk-size", type=int, metavar="N",
                          help="largest chunk, >= frames per pose; each pose is published as its own chunk "
                               "[chunk_size]")
    settings.add_argument("--initial-views", type=int, metavar="N",
                          help="adaptive: well-spread views taken before any ranking is used [initial_views]")
    settings.add_argument("--stop-when-converged", action="store_const", const=True, default=None,
                          help="adaptive: end the scan once the live reconstruction reports convergence; its "
                               "refits restart that test, so only a paused or slow scan (a pose every 13 s or "
                               "more with 32 views in, 6.5 s or more past 64) ends early [stop_when_converged]")
    pause = op("pause", "pause once the poses under way (one captured, one being written) are published")
    resume = op("resume", "continue a paused or interrupted scan at its first unpublished pose",
                "Continue the paused scan at its first unpublished pose. With NAME, or when the daemon holds no "
                "scan: take over an interrupted scan it could not take over when it started (`status` says why, "
                "e.g. a damaged chunk to move out of the folder first), then continue it: the poses of a chunk "
                "moved out are taken again first (the arm goes back along the scan's path), so the scan still ends "
                "complete with every pose.")
    resume.add_argument("name", nargs="?", metavar="NAME", help="an interrupted scan the daemon does not hold")
    abort = op("abort", "stop the scan for good (published poses stay)",
               "Stop the scan for good; its published poses stay. With NAME: end an interrupted scan the daemon does "
               "not hold (one it could not take over, `status` says why) as aborted, every chunk kept. Exits 1 when "
               "the disk could not record the abort yet (full or read-only): the reply says what keeps it, and the "
               "daemon writes it again until it lands.")
    abort.add_argument("name", nargs="?", metavar="NAME", help="an interrupted scan the daemon does not hold")
    abort.add_argument("--reason", help="why (recorded in the capture)")
    wait = op("wait", "block until scan NAME is complete (exit 0) or aborted (exit 1)",
              "Block until scan NAME is complete (exit 0) or aborted (exit 1), then print the daemon's answer as JSON "
              "({\"name\", \"state\"}, and \"reason\" where one was given for how it ended, as the daemon that "
              "ended it recorded it (its folder says it for a scan that ended before the daemon started); an aborted "
              "scan's last line on stderr gives it). On a terminal a progress bar runs on stderr (with a rate and a "
              "time left only while the scan scans, and how its live reconstruction stands: e.g. queued behind "
              "another job); otherwise a line on stderr says why whenever the scan pauses, and how the live "
              "reconstruction goes (queued, waiting for views, following the scan, finishing ...). Ctrl-C stops "
              "only the waiting (exit 130): the scan goes on in the daemon.")
    wait.add_argument("name", metavar="NAME", help="the scan's name (its folder under the captures root)")
    shutdown = op("shutdown", "stop the daemon; a scan in flight stays resumable")
    status.add_argument("--json", action="store_true",
                        help="the same JSON as without it, on one line (as every operation's --json prints its "
                             "reply); a refusal, or no daemon answering, is printed as {\"ok\": false, "
                             "\"error\": ...} too, beside its error line and exit status 1")
    wait.add_argument("--json", action="store_true",
                      help="for scripts: standard output gets one line of JSON once the wait ends, and nothing "
                           "else: the daemon's status as the scan ended, as `status --json` prints it (the next scan "
                           "may run by then: the line is still the status of the scan waited for, with its `live`; "
                           "for a scan that ended before the daemon started, the daemon's status then, with the "
                           "waited scan's `live`: `state` is always the daemon's), plus `wait`: {\"name\", "
                           "\"ended\": complete or aborted, \"reason\" where one was given for how it ended, "
                           "\"waited_s\"}; an error (a refusal, no daemon answering, --timeout run out) or "
                           "Ctrl-C is printed as {\"ok\": false, \"error\": ..., \"wait\": {\"name\", \"ended\": "
                           "error, timeout or interrupted, \"waited_s\"}} beside its line on stderr. The exit status "
                           "is as without --json (0 complete; 1 aborted or an error; 130 Ctrl-C). The progress bar "
                           "(on a terminal) or the pause and live notes stay on stderr, for the person or the log "
                           "watching")
    for answering in (scan, pause, resume, abort, shutdown):  # what they did, in one line for people
        answering.add_argument("--json", action="store_true",
                               help="print the daemon's whole reply as one line of JSON (for scripts), not the "
                                    "one-line summary; a refusal too, as {\"ok\": false, \"error\": ...}, beside "
                                    "its error line and exit status 1")


def run(args) -> int:
    from spadscan.daemon.client import ControlError, call, default_socket_path

    path = default_socket_path(create=False) if args.socket is None else args.socket
    timeout = REPLY_TIMEOUT_S.get(args.op, 30.0) if args.timeout is None else args.timeout
    if args.op == "wait":
        return _wait(path, args.name, args.timeout, args.json)
    request = {}
    if args.op == "scan":
        options = {key: getattr(args, opt) for opt, (key, _) in SCAN_OPTIONS.items() if getattr(args, opt) is not None}
        request = {"options": options, **({"name": args.name} if args.name is not None else {})}
    elif args.op in ("resume", "abort"):
        request = {key: value for key, value in (("name", args.name), ("reason", getattr(args, "reason", None)))
                   if value}
    try:
        check_socket(path)
        reply = call(path, args.op, timeout, **request)
    except ControlError as exc:
        if getattr(args, "json", False):  # a script that reads standard output reads the refusal there too
            print(json.dumps({"ok": False, "error": str(exc)}))
        raise
    if args.op == "status":
        reply = status_dict(reply)
    reply.pop("ok", None)
    if args.op == "status":  # for people, indented; with --json one line, as every operation's --json
        print(json.dumps(reply) if args.json else json.dumps(reply, indent=1))
    else:
        print(json.dumps(reply) if args.json else reply_line(args.op, reply))
    if args.op == "abort" and reply.get("abort_recorded") is False:
        # The scan is over in the daemon, but not on disk yet: a script must not take that for a done abort.
        said = reply.get("last_error") or f"the abort of scan {reply.get('aborted')!r} is not recorded on disk yet"
        print(f"spadscan: error: {said}", file=sys.stderr)
        return 1
    if args.op == "scan" and args.wait:
        return _wait(path, reply["scan"], args.timeout, args.json)
    return 0


def check_socket(path: str) -> None:
    """A ControlError when `path` is there but is no socket (a file, a folder): the connection would be refused as
    if no daemon were listening, and the user would look for a daemon instead of at the path. A missing path is left
    to the connection's own error."""
    from spadscan.daemon.client import ControlError

    try:
        mode = os.stat(path).st_mode
    except OSError:
        return
    if stat.S_ISSOCK(mode):
        return
    what = "a folder" if stat.S_ISDIR(mode) else "a file" if stat.S_ISREG(mode) else "something else"
    raise ControlError(f"{path} is {what}, not a socket: no daemon listens there (pass --socket the daemon's control "
                       f"socket, its config's `socket` key)")


def reply_line(op: str, reply: dict) -> str:
    """One line for people about the daemon's reply to `op` (scan, pause, resume, abort: the daemon's status after
    it; shutdown): the scan in hand, its state and its pose i/n (and, for a pause, the pose it stops at; for a paused
    scan, why), the scan an abort ended and the pose it stopped at, where a scan started is written."""
    if op == "shutdown":
        return "the daemon is stopping (a scan in flight stays resumable)"
    said = []
    aborted, name = reply.get("aborted"), reply.get("scan")
    if aborted:
        note = reply.get("abort_note") or ("not recorded on disk yet" if reply.get("abort_recorded") is False
                                          else None)
        at = f" at pose {reply['progress']}" if reply.get("progress") and not name else ""  # (else `name`'s pose)
        said.append(f"scan {aborted!r} aborted{at}" + (f" ({note})" if note else ""))
    if name:
        line = f"scan {name!r} {reply.get('state')} at pose {reply.get('progress')}"
        if reply.get("pausing_at"):
            line += f" (it stops at pose {reply['pausing_at']}, once the poses under way are published)"
        if reply.get("reason"):
            line += f": {reply['reason']}"
        said.append(line)
        again = reply.get("poses_to_take_again")
        if again:  # poses missing from the capture (a damaged chunk moved out): taken again before it goes on
            said.append(f"taking pose(s) {', '.join(str(p) for p in again)} again first")
        if op == "scan" and reply.get("path"):
            said.append(f"written to {reply['path']}")
        if op in ("scan", "resume") and reply.get("speed_note"):  # why the scan will crawl
            said.append(reply["speed_note"])
    elif not aborted:
        said.append(f"the daemon is {reply.get('state')}, with no scan in hand")
    return "; ".join(said)


def status_dict(reply: dict) -> dict:
    """What `status` prints of the daemon's status reply: the reply without its `ok`, with `live` (`live_status`)
    when the scan has a live reconstruction."""
    shown = {k: v for k, v in reply.items() if k != "ok"}
    live = live_status(shown)
    if live is not None:
        shown["live"] = live
    return shown


def _wait(path: str, name: str, timeout: float | None, as_json: bool = False) -> int:
    """`wait`: the daemon's reply on standard output (with `as_json`, the `wait_json` line instead); exit 0 for a
    complete scan, 1 for an aborted one or an error, 130 for Ctrl-C. With `as_json` an error (and Ctrl-C) is a
    {"ok": false, "error", "wait"} line on standard output too, beside its line on stderr."""
    from spadscan.daemon.client import ControlTimeout
    from spadscan.protocol.errors import SpadscanError

    began = time.monotonic()

    def waited(ended: str) -> dict:
        return {"name": name, "ended": ended, "waited_s": round(time.monotonic() - began, 1)}

    try:
        reply = wait_for_scan(path, name, timeout, sys.stderr)
    except KeyboardInterrupt:
        # Only this client stops waiting: the daemon drops the abandoned request and the scan goes on.
        said = (f"interrupted; scan {name!r} goes on in the daemon (`spadscan ctl wait {name}` waits again, "
                f"`spadscan ctl abort` stops it)")
        if as_json:
            print(json.dumps({"ok": False, "error": said, "wait": waited("interrupted")}), flush=True)
        print(f"spadscan: {said}", file=sys.stderr)
        return 130
    except SpadscanError as exc:
        if as_json:  # a script that reads standard output reads the error there too
            ended = "timeout" if isinstance(exc, ControlTimeout) else "error"
            print(json.dumps({"ok": False, "error": str(exc), "wait": waited(ended)}))
        raise
    reply.pop("ok", None)
    status = reply.pop("status", None)  # (the daemon's status as the scan ended: for --json alone)
    line = reply
    if as_json:
        try:
            ended = {**waited(str(reply.get("state"))), **({"reason": reply["reason"]} if reply.get("reason") else {})}
            line = wait_json(reply, _status(path) if status is None else status, ended)
        except KeyboardInterrupt:  # the scan has ended: a Ctrl-C while its live status is read leaves the status out
            line = {"wait": ended}
    print(json.dumps(line))
    if reply.get("state") != "complete":
        reason = reply.get("reason")  # (an abort's: `ctl abort --reason`, or the daemon's own)
        print(f"spadscan: scan {name!r} ended {reply.get('state')}" + (f": {reason}" if reason else ""),
              file=sys.stderr)
        return 1
    return 0


def wait_json(reply: dict, status: dict, waited: dict) -> dict:
    """`wait --json`'s line: `status`, the daemon's status as the scan waited for ended (from the wait's reply: one
    read afterwards may be the next scan's; for a scan that ended before the daemon started, which the daemon has no
    such status of, the status it answers now; {} when it answers no more), as `status --json` prints it, its `live`
    that scan's whatever scan the daemon held; and `wait`: {"name", "ended": the scan's end (complete, aborted),
    "reason" where one was given, "waited_s"}. Its `state` is the daemon's in every case: the scan's end is
    `wait`'s."""
    shown = {k: v for k, v in status.items() if k not in ("ok", "live")}
    captures = (status.get("daemon") or {}).get("captures")
    live = capture_live(os.path.join(captures, reply["name"]), captures) if captures else None
    if live is not None:
        shown["live"] = live
    return {**shown, "wait": waited}


def wait_for_scan(path: str, name: str, timeout: float | None, stream) -> dict:
    """The `wait` reply for scan `name`. The blocking `wait` request runs on a thread while `status` is polled every
    PROGRESS_POLL_S seconds: on a terminal `stream` shows a progress bar (poses published / planned, state, pause
    reason); otherwise it gets one line each time the scan pauses, so that a script's log says why it blocks. A
    `wait` that runs out of time says how far the scan got."""
    import threading

    from spadscan.daemon.client import ControlTimeout, call

    check_socket(path)
    outcome: dict = {}

    def wait() -> None:
        try:
            outcome["reply"] = call(path, "wait", timeout, name=name)
        except BaseException as exc:  # re-raised on the main thread
            outcome["error"] = exc

    waiter = threading.Thread(target=wait, name="ctl wait", daemon=True)
    waiter.start()
    shown = ProgressBar(name, stream) if stream.isatty() else PauseNotes(name, stream)
    try:
        waiter.join(PROGRESS_POLL_S)  # a scan that is already over needs no status
        while waiter.is_alive():
            shown.update(_status(path))
            waiter.join(PROGRESS_POLL_S)
        shown.finish(outcome.get("reply", {}).get("state"))
    finally:
        shown.close()
    error = outcome.get("error")
    if isinstance(error, ControlTimeout):
        raise _still_running(path, name, timeout) or error
    if error is not None:
        raise error
    return outcome["reply"]


def live_capture(status: dict) -> str | None:
    """The capture folder of the scan a daemon status is about: the scan in flight, else the last one."""
    if status.get("path"):
        return str(status["path"])
    last = (status.get("last_scan") or {}).get("name")
    captures = (status.get("daemon") or {}).get("captures")
    return os.path.join(captures, last) if last and captures else None


def live_status(status: dict) -> dict | None:
    """The live reconstruction of the scan a daemon status is about, as a dict (recon/live/status.json with
    `age_s`, or {'error': why} when that file cannot be read), with `queued` (`live_queued`) while its live job waits
    in the worker's queue (then the whole dict before its first status); None when there is none of either."""
    capture = live_capture(status)
    if capture is None:
        return None
    return capture_live(capture, (status.get("daemon") or {}).get("captures"))


def capture_live(capture: str, captures: str | None) -> dict | None:
    """`live_status` of the scan whose capture folder is `capture`, under captures root `captures` (None: its queue is
    not read)."""
    live = _live_file(capture)
    queued = live_queued(captures, os.path.basename(capture)) if captures else None
    if queued is not None:
        return {**(live or {}), "queued": queued}
    gone = live_job_gone(captures, live) if captures and live else None
    return {**live, "gone": gone} if gone else live


def live_job_gone(captures: str, live: dict) -> str | None:
    """Why the live reconstruction a live status says follows its scan (or runs its final run) is not running: its
    job's worker is gone (the queue's 'stale' or 'running?', as `spadscan worker --status` says); None while it runs,
    once its job left running/ (it ended: its status is written just after; or it was queued again, which
    `live_queued` says), or where the queue cannot be read. The status file is its job's last word: a worker killed
    mid-scan leaves it saying 'live' for good."""
    from spadscan.protocol.errors import SpadscanError
    from spadscan.worker.queue import Queue
    from spadscan.worker.status_detail import FOLLOWING

    if live.get("state") not in FOLLOWING or not live.get("job"):
        return None
    try:
        queue = Queue.for_root(captures, create=False)
        row = next((r for r in queue.statuses(("running",)) if r.id == live["job"]), None)
    except (OSError, SpadscanError):
        return None
    if row is not None and row.stale:
        return f"its job {live['job']} is {row.shown_state}: {row.stale}"
    return None


def _live_file(capture: str) -> dict | None:
    """`capture`'s recon/live/status.json as a dict with `age_s` ({'error': why} when unreadable), or None."""
    from spadscan.protocol.errors import CaptureError
    from spadscan.protocol.live_status import read_status, status_path

    if not status_path(capture).exists():
        return None
    try:
        live = read_status(status_path(capture))
    except CaptureError as exc:
        return {"error": str(exc)}
    age = live.age_s()
    return {**live.to_dict(), "age_s": None if age is None else round(age, 1)}


def live_queued(captures: str, scan: str) -> dict | None:
    """Scan `scan`'s live job while it waits in the worker's queue under captures root `captures` (its default
    queue: a worker started with `--queue DIR` is not seen), as {"job": its id, "waiting_s": seconds since it was
    queued (or given back), "behind": the jobs of other scans running now (their workers renew their claims),
    "workers": the workers present ("HOST pid N"), "processes": how many jobs they run at once, "room_waits": the
    workers among them that wait for room on a full disk before they claim again, each one's `room_wait`
    (presence.Presence.room_wait), "said": what it waits for, in the dashboard's words: room on a full disk where
    every worker waits for it or a queued job's wait holds every claim (Queue.room_waits), whatever the workers
    say}; None when it is not queued, or the queue cannot be read. The worker's own queue and presence code read it,
    as for the dashboard and `spadscan worker --status`."""
    from spadscan.protocol.errors import SpadscanError
    from spadscan.worker.presence import present_workers, start_command
    from spadscan.worker.queue import Queue

    try:
        queue = Queue.for_root(captures, create=False)
        live = next((job.id for job in queue.queued_jobs() if job.scan == scan and job.live), None)
        if live is None:
            return None  # (polled every PROGRESS_POLL_S by `wait`: no more is read unless the live job waits)
        rows = queue.statuses(states=("queued", "running"))
        job = next((row for row in rows if row.state == "queued" and row.id == live), None)
        if job is None:  # claimed meanwhile
            return None
        workers = present_workers(queue.path)
    except (OSError, SpadscanError):  # no queue, or one this user may not read: nothing to say of it
        return None
    behind = [row.id for row in rows if row.state == "running" and row.stale is None and row.scan != scan]
    named = [{"name": f"{w['host']} pid {w['pid']}", "processes": w["processes"], "running": w["running"],
              "room_wait": w.get("room_wait")} for w in workers]
    try:  # a queued job's wait for room holds every claim, whatever the workers say (Queue.room_waits)
        held = list(queue.room_waits())
    except OSError:
        held = []
    return {"job": job.id, "waiting_s": None if job.waiting_s is None else round(job.waiting_s, 1), "behind": behind,
            "workers": [w["name"] for w in named], "processes": sum(w["processes"] for w in named),
            "room_waits": {w["name"]: w["room_wait"] for w in named if w["room_wait"] is not None},
            "said": queued_said(behind, named, f"{start_command(Path(captures), queue.path)} --live", held)}


def queued_said(behind: list[str], workers: list[dict], start: str, held: list[tuple[str, dict]] = ()) -> str:
    """What a queued live job waits for, as the dashboard says it: room on a full disk (every worker waits for it, or
    a queued job's wait holds every claim: `held`, (job id, its wait) for each job given back to the queue on a full
    disk whose room is still missing, Queue.room_waits; disk_room.holding_said, which says to start a worker with
    `start` where none is present), no worker (and `start`, the command that starts one), a worker's next look (a
    job process is free), or the jobs `behind` (and how to run one job more at once). A worker that waits for room
    (its `room_wait`, as the worker reads it: a damaged one is none) claims nothing meanwhile: neither its job
    processes nor the jobs it runs count."""
    from spadscan.worker.disk_room import RoomWait, holding_said, names_said

    def waits(worker: dict) -> bool:
        return RoomWait.from_note(worker.get("room_wait"), skewed=True) is not None

    said = holding_said([w["room_wait"] for w in workers if waits(w)], held, len(workers), start=start)
    if said is not None:
        return said
    if not workers:
        return f"no worker is running: start one with `{start}`"
    claiming = [w for w in workers if not waits(w)]
    held_jobs = {job for w in workers if waits(w) for job in w.get("running", ())}
    behind = [job for job in behind if job not in held_jobs]
    n = sum(w["processes"] for w in claiming) or 1
    if len(behind) < n:
        return "a worker takes it at its next look"
    return (f"waiting for {'' if len(behind) == 1 else 'one of '}{names_said(behind)} to finish "
            f"({_processes_advice(claiming, n)})")


def room_said(waits: list[dict], queue_waits: list[dict] = ()) -> str | None:
    """What a queued job waits for while every worker waits for room (`waits`: their `room_wait`s; `queue_waits`:
    those of the jobs given back to the queue on a full disk whose room is still missing), worded as the worker's own
    lines, `worker --status` and the dashboard word it (disk_room.room_said); None where no wait is read."""
    from spadscan.worker.disk_room import room_said as worded

    return worded(waits, queue_waits)


def _processes_advice(workers: list[dict], n: int) -> str:
    """What runs one job more at once: --processes is each worker's own, so with several workers it names the one
    that runs the fewest (or one more worker)."""
    if len(workers) == 1:
        return f"the worker runs {_plural(n, 'job')} at a time; `--processes {n + 1}` runs {n + 1}"
    least = min(workers, key=lambda w: w["processes"])  # the first of those that run the fewest
    return (f"the {len(workers)} workers run {_plural(n, 'job')} at a time; one more worker, or `--processes "
            f"{least['processes'] + 1}` for the worker on {least['name']}, runs {n + 1}")


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def live_line(live: dict | None, scan_views: int | None = None) -> str | None:
    """One line for people about a live reconstruction dict (`live_status`), or None. `scan_views`: the views the
    scan has published by the daemon's count (its status's `pose`): a live fit that follows it says how far behind it
    is, which its own count of views published (those it last read) does not. A live job waiting in the queue says
    what for."""
    if not live:
        return None
    said = _fit_line(live, scan_views)
    if live.get("gone"):
        return f"{said or 'live reconstruction'}; {live['gone']}"
    queued = live.get("queued")
    if not isinstance(queued, dict):
        return said
    if said is None:  # no status written yet: the job has not started
        return f"live reconstruction queued: {queued['said']}"
    # a status that says 'queued again' says why; one that says otherwise is an earlier attempt's
    return f"{said}; {'' if live.get('state') == 'queued' else 'its job is queued: '}{queued['said']}"


def _fit_line(live: dict, scan_views: int | None) -> str | None:
    """`live_line` of the live status file alone."""
    if "error" in live:
        return f"live: {live['error']}"
    from spadscan.protocol.live_status import LiveStatus

    known = {k: v for k, v in live.items() if k in LiveStatus.__dataclass_fields__}
    try:
        said = LiveStatus(**known).summary()
    except TypeError:
        return None
    seen = live.get("views_published")
    if (live.get("state") in ("waiting", "live") and isinstance(scan_views, int) and isinstance(seen, int)
            and scan_views > seen):
        said += f"; the scan has published {scan_views} views"
    return said


def _status(path: str) -> dict:
    """The daemon's status, or {} when it does not answer (the `wait` request then says what went wrong)."""
    from spadscan.daemon.client import ControlError, call

    try:
        return call(path, "status", 10.0)
    except ControlError:
        return {}


def _still_running(path: str, name: str, timeout: float):
    """The error for a `wait` that timed out on a scan that is still going (a ControlTimeout; None when the daemon
    says otherwise)."""
    from spadscan.daemon.client import ControlTimeout

    status = _status(path)
    if status.get("scan") != name:
        return None
    reason = status.get("reason")
    return ControlTimeout(f"scan {name!r} still {status.get('state')} at pose {status.get('progress')} after "
                          f"{timeout:g} s" + (f" ({reason})" if reason else ""))


class PauseNotes:
    """Without a terminal: one line on the stream each time scan `name` pauses, with the reason and, where the reason
    does not say it already (RESUME_SAID), that `spadscan ctl resume` continues the scan."""

    RESUME_SAID = ("`spadscan ctl resume", "`spadscan ctl abort")
    """A reason that names either already says how the scan goes on (or that only an abort ends it)."""

    def __init__(self, name: str, stream):
        self.name, self.stream = name, stream
        self.noted = False
        self.live_said = None  # the live reconstruction's state, and what its queued job waits for, last said

    def update(self, status: dict) -> None:
        paused = status.get("scan") == self.name and status.get("state") == "paused"
        if paused and not self.noted:
            reason = status.get("reason") or "no reason given"
            advice = "" if any(said in reason for said in self.RESUME_SAID) else " (`spadscan ctl resume` continues it)"
            print(f"spadscan: scan {self.name!r} paused at pose {status.get('progress')}: {reason}{advice}",
                  file=self.stream, flush=True)
        self.noted = paused
        live = live_status(status) if status.get("scan") == self.name else None
        # a line when the live reconstruction is queued, starts, finishes or ends, or waits for something else
        said = (live.get("state"), (live.get("queued") or {}).get("said")) if live else None
        if said not in (None, (None, None)) and said != self.live_said:
            print(f"spadscan: scan {self.name!r} {live_line(live)}", file=self.stream, flush=True)
        self.live_said = said if said not in (None, (None, None)) else self.live_said

    def finish(self, state: str | None) -> None:
        pass

    def close(self) -> None:
        pass


class ProgressBar:
    """On a terminal: a progress bar of scan `name` (tqdm, imported only here: `ctl status` and friends stay
    light). It starts at the pose the scan is at and advances by the poses published since, so that its rate counts
    only poses it saw taken (a `wait` begun mid-scan would count the earlier ones as taken in its first second).
    While the scan is not scanning (paused, pausing) it shows no rate and no time left: a pause has no end time.
    On resume its timer restarts, so that the pause's time does not drag the rate down afterwards (nor count as time
    taken)."""

    SCANNING = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_fmt}, %s]"
    STILL = "{l_bar}{bar}| {n_fmt}/{total_fmt} [%s]"

    def __init__(self, name: str, stream):
        self.name, self.stream = name, stream
        self.bar = None
        self.state = None  # the scan's state at the last update

    def update(self, status: dict) -> None:
        if status.get("scan") != self.name:
            return
        scanning = status.get("state") == "scanning"
        reason = status.get("reason")
        live = live_line(live_status(status), status.get("pose"))
        shown = self._format(scanning, status["state"] + (f": {reason}" if reason else "") +
                             (f"; {live}" if live else ""))
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=status["poses"], initial=status["pose"], desc=self.name, unit="pose",
                            file=self.stream, dynamic_ncols=True, bar_format=shown)
        else:
            if scanning and self.state == "paused":
                self.bar.unpause()  # the time paused is no time spent scanning
            self.bar.bar_format = shown
        self.state = status["state"]
        taken = status["pose"] - self.bar.n
        if taken > 0:
            self.bar.update(taken)
        elif taken < 0:  # (never expected: a pose count that goes back is shown as it is)
            self.bar.n = status["pose"]
        self.bar.refresh()

    def _format(self, scanning: bool, text: str) -> str:
        """The bar's format: the counts, then (only while scanning) the time taken, the time left and the rate,
        then `text`."""
        text = text.replace("{", "{{").replace("}", "}}")  # the text goes into a format string as it is
        return (self.SCANNING if scanning else self.STILL) % text

    def finish(self, state: str | None) -> None:
        if self.bar is not None and state == "complete":
            self.bar.n = self.bar.total
            self.bar.bar_format = self._format(False, "complete")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
