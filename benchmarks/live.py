"""Live reconstruction against today's offline job: how long after the scan's last pose the final mesh is in place,
at what Chamfer, and what a live job costs the daemon per pose.

    python benchmarks/live.py [--scenes demo,teddy,mug] [--views N] [--out FOLDER] [--frame-time-s S]

Each scene is scanned twice by a real `spadscan daemon` with the real rig's defaults (the sim arm at the default
speed and acceleration, moves timed from their distance; settle time, views and schedule as the [scan] defaults; a
simulated TMF8820 delivering a frame every --frame-time-s, 0.33 s: the real sensor gives 2-4 frames a second):

- alone, with no worker: today's offline job (`spadscan worker --once`, the preset's defaults) then reconstructs the
  capture, timed from its start, which is when it could start at the earliest: the scan's end;
- with `spadscan worker --live` running from the start: timed from the moment the manifest says complete (the
  benchmark polls it every 0.1 s) to the moment the final result folder is in place.

Both scans follow the same plan and render the same frames, so their durations, taken from the capture's own frame
timestamps (the daemon's clock), give the daemon's time per pose with and without a live job beside it. On the first
scene the daemon's own per-pose overhead (benchmarks/daemon_overhead.py: moves and frames of zero time, so that only
the daemon's work counts) is measured too, alone and again while the live job trains. Every figure is printed side
by side with its peer; the JSON of every run goes to --out. Goal: the final mesh within 30 s
of the scan's end on 2 cores, at a Chamfer no worse than the offline job's.

The daemon and the workers stop with the benchmark: on Ctrl-C or SIGTERM it stops them (and prints the scenes
measured so far); killed outright, it leaves them to notice that it is gone (spadscan/parent_watch.py).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from spadscan import parent_watch
from spadscan.daemon.client import ControlError, call
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.child_command import module_command
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.live_status import read_status, status_path

GOAL_S = 30.0
SCENES = ("demo", "teddy", "mug")


def spadscan(*args) -> list[str]:
    return module_command("spadscan.cli", *args)


def rig_text(captures: Path, sock: Path, scene: str, views: int | None, frame_time_s: float,
             time_scale: float) -> str:
    """The real rig's defaults, with simulated devices: only what a simulation needs is set."""
    scan = f"views = {views}\n" if views is not None else ""
    return (f'captures = "{captures}"\nsocket = "{sock}"\n\n'
            f'[arm]\nbackend = "sim"\ntime_scale = {time_scale}\n\n'
            f'[sensor]\nbackend = "sim"\nmesh = "builtin:{scene}"\nframe_time_s = {frame_time_s}\n\n'
            f"[scan]\n{scan}")


class Rig:
    """A daemon (and optionally a worker) on one captures root, stopped on exit."""

    def __init__(self, folder: Path, scene: str, args):
        self.folder = folder
        self.captures = folder / "captures"
        self.captures.mkdir(parents=True)
        self.sock_dir = Path(tempfile.mkdtemp(prefix="spadscan-live-"))
        self.sock = self.sock_dir / "ctl.sock"
        rig = folder / "rig.toml"
        rig.write_text(rig_text(self.captures, self.sock, scene, args.views, args.frame_time_s, args.time_scale))
        self.procs: list[subprocess.Popen] = []
        self.daemon = self.start("daemon", spadscan("daemon", "--config", rig))
        deadline = time.monotonic() + 120
        try:
            while True:
                try:
                    call(self.sock, "status", timeout_s=5)
                    break
                except ControlError:
                    if self.daemon.poll() is not None or time.monotonic() > deadline:
                        raise SystemExit(f"the daemon did not start (log: {folder / 'daemon.log'})") from None
                    time.sleep(0.1)
        except BaseException:  # no caller holds this rig yet to close it
            self.close()
            raise

    def start(self, name: str, argv: list[str], env: dict | None = None) -> subprocess.Popen:
        # Named as their parent (parent_watch): killed outright, the benchmark cannot stop them, and they stop
        # themselves.
        with open(self.folder / f"{name}.log", "ab") as log:
            proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    env=parent_watch.child_env({**os.environ, **(env or {})}))
        self.procs.append(proc)
        return proc

    def close(self) -> None:
        for proc in reversed(self.procs):
            if proc.poll() is None:
                proc.terminate()
        for proc in reversed(self.procs):
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        shutil.rmtree(self.sock_dir, ignore_errors=True)


def run_to_end(argv: list[str], log: Path, env: dict) -> int:
    """Run `argv` to its end (output to `log`); its exit status. Stopped (Ctrl-C, SIGTERM), it is stopped as `kill
    PID` stops it, so that a worker hands its job back (subprocess.run would kill it outright), and killed outright,
    it stops by itself (parent_watch)."""
    with open(log, "wb") as f:
        proc = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                env=parent_watch.child_env({**os.environ, **env}))
    try:
        return proc.wait()
    except BaseException:
        proc.terminate()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        raise


OVERHEAD_ROW = re.compile(r"per-pose overhead, K=1, (?P<what>[^<]+?)\s{2,}<[^m]+ms\s+(?P<ms>[\d.]+) ms")


def daemon_overhead(folder: Path, poses: int) -> dict:
    """benchmarks/daemon_overhead.py's per-pose overhead figures (ms, by run), its captures under `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    r = subprocess.run([sys.executable, str(Path(__file__).with_name("daemon_overhead.py")), "--dir", str(folder),
                        "--poses", str(poses), "--frames", "8"], capture_output=True, text=True,
                       env=parent_watch.child_env())
    if r.returncode != 0:
        raise SystemExit(f"daemon_overhead.py failed: {r.stderr.strip().splitlines()[-1:]}")
    return {m["what"].strip(): float(m["ms"]) for m in OVERHEAD_ROW.finditer(r.stdout)}


def scan_and_follow(rig: Rig, name: str, capture: Path, live: bool, timeout_s: float,
                    while_live=None) -> dict:
    """Start the scan, poll its manifest (and live status) every 0.1 s; returns when the scan is complete and, with
    `live`, when its final result is in place. `while_live()` runs once the live job has fitted views (the scan
    goes on meanwhile); its result is returned as `while_live`."""
    call(rig.sock, "scan", timeout_s=30, name=name, options={})
    t0 = time.monotonic()
    ended = None
    trace = []
    extra = None
    result = capture / "recon" / f"{name}-fast" / "report.json"
    while time.monotonic() - t0 < timeout_s:
        now = time.monotonic()
        if ended is None:
            try:
                state = CaptureReader(capture).state
            except CaptureError:
                state = None
            if state == "complete":
                ended = now
            elif state == "aborted":
                raise SystemExit(f"scan {name} was aborted (log: {rig.folder / 'daemon.log'})")
        if live:
            try:
                st = read_status(status_path(capture))
                if not trace or trace[-1]["updated_utc"] != st.updated_utc:
                    trace.append({"t_s": round(now - t0, 2), **st.to_dict()})
                if while_live is not None and extra is None and st.state == "live" and ended is None:
                    extra = while_live()
                    continue
            except CaptureError:
                pass
            if ended is not None and result.exists() and _daemon_done(rig, name):
                return {"scan_wall_s": ended - t0, "after_end_s": now - ended, "trace": trace, "while_live": extra}
        elif ended is not None and _daemon_done(rig, name):
            return {"scan_wall_s": ended - t0}
        time.sleep(0.1)
    raise SystemExit(f"{name}: nothing after {timeout_s:.0f} s (logs in {rig.folder})")


def _daemon_done(rig: Rig, name: str) -> bool:
    """The daemon has recorded the scan's end (stopping it before then could leave the scan to resume)."""
    status = call(rig.sock, "status", timeout_s=30)
    return (status.get("last_scan") or {}).get("name") == name and status.get("state") == "idle"


def frame_clock(capture: Path) -> dict:
    """The scan's duration on the daemon's own clock: first frame's start to last frame's end."""
    data = CaptureReader(capture).load()
    starts = [m["t_start"] for m in data.meta if "t_start" in m]
    ends = [m["t_end"] for m in data.meta if "t_end" in m]
    views = len(set(data.pose_indices.tolist()))
    span = max(ends) - min(starts)
    return {"views": views, "scan_s": span, "per_pose_s": span / max(1, views - 1)}


def report_of(capture: Path, job: str) -> dict:
    return json.loads((capture / "recon" / job / "report.json").read_text())


def run_scene(scene: str, out: Path, args) -> dict:
    name = scene
    row = {"scene": scene}
    overhead = args.overhead_poses if scene == args.scenes.split(",")[0] else 0
    if overhead:
        row["overhead_alone_ms"] = daemon_overhead(out / scene / "overhead-alone", overhead)
    # 1. Alone, then today's offline job on its capture.
    rig = Rig(out / scene / "alone", scene, args)
    try:
        scan_and_follow(rig, name, rig.captures / name, live=False, timeout_s=args.timeout_s)
    finally:
        rig.close()
    capture = rig.captures / name
    row["alone"] = frame_clock(capture)
    env = {"OMP_NUM_THREADS": str(args.threads)} if args.threads else {}
    t = time.monotonic()
    budget = ["--budget-s", args.offline_budget_s] if args.offline_budget_s else []
    status = run_to_end(spadscan("worker", "--root", rig.captures, "--once", "--poll-s", 0.5, *budget),
                        out / scene / "alone" / "worker.log", env)
    row["offline_s"] = time.monotonic() - t
    if status != 0:
        raise SystemExit(f"{scene}: the offline worker failed (log: {out / scene / 'alone' / 'worker.log'})")
    offline = report_of(capture, f"{name}-fast")
    row["offline"] = {k: offline.get(k) for k in ("chamfer_mm", "steps", "seconds", "stopped_by", "wall_seconds")}

    # 2. With a live worker from the start.
    rig = Rig(out / scene / "live", scene, args)
    try:
        budget = ["--budget-s", args.final_budget_s] if args.final_budget_s else []
        rig.start("worker", spadscan("worker", "--root", rig.captures, "--live", "--poll-s", 0.5, *budget), env)
        measure = (lambda: daemon_overhead(out / scene / "overhead-live", overhead)) if overhead else None
        followed = scan_and_follow(rig, name, rig.captures / name, live=True, timeout_s=args.timeout_s,
                                   while_live=measure)
    finally:
        rig.close()
    capture = rig.captures / name
    row["with_live"] = frame_clock(capture)
    final = report_of(capture, f"{name}-fast")
    row["live_s"] = followed["after_end_s"]
    row["live"] = {k: final.get(k) for k in ("chamfer_mm", "steps", "seconds", "stopped_by", "wall_seconds", "live")}
    at_end = [t for t in followed["trace"] if t["state"] in ("live", "final")]
    row["live_chamfer_at_scan_end_mm"] = at_end[-1].get("chamfer_mm") if at_end else None
    row["live_trace"] = followed["trace"]
    if overhead:
        row["overhead_with_live_ms"] = followed["while_live"]
    (out / scene / "row.json").write_text(json.dumps(row, indent=1) + "\n")
    return row


def fmt(v, spec: str = ".2f") -> str:
    return "-" if v is None else format(v, spec)


def table(rows: list[dict]) -> str:
    head = ("| scene | views | scan | s/pose alone | s/pose with live | live: mesh after scan end | live Chamfer mm | "
            "offline: mesh after scan end | offline Chamfer mm | live Chamfer at scan end |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        a, w = r["alone"], r["with_live"]
        lines.append(f"| {r['scene']} | {a['views']} | {a['scan_s']:.0f} s | {a['per_pose_s']:.3f} s | "
                     f"{w['per_pose_s']:.3f} s | {r['live_s']:.1f} s | {fmt(r['live']['chamfer_mm'])} | "
                     f"{r['offline_s']:.1f} s | {fmt(r['offline']['chamfer_mm'])} | "
                     f"{fmt(r['live_chamfer_at_scan_end_mm'])} |")
    for r in rows:
        if r.get("overhead_alone_ms") and r.get("overhead_with_live_ms"):
            lines.append("")
            with_live = r["overhead_with_live_ms"]
            lines.append(f"daemon per-pose overhead (daemon_overhead.py, during the {r['scene']} scan): " + "; ".join(
                f"{what}: alone {ms:.2f} ms, with a live job {with_live.get(what, float('nan')):.2f} ms"
                for what, ms in r["overhead_alone_ms"].items()))
    return "\n".join(lines)


def machine_note() -> str:
    load = os.getloadavg()
    return f"{os.cpu_count()} cores, load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} (1 / 5 / 15 min)"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=",".join(SCENES), help=f"built-in scenes (default {','.join(SCENES)})")
    ap.add_argument("--views", type=int, default=None, help="views per scan (default: the daemon's, 128)")
    ap.add_argument("--frame-time-s", type=float, default=0.33,
                    help="seconds per simulated frame (default 0.33: the TMF8820 gives 2-4 frames a second)")
    ap.add_argument("--time-scale", type=float, default=1.0,
                    help="multiplies the sim arm's motion times (default 1: the real arm's speed)")
    ap.add_argument("--final-budget-s", type=float, default=None,
                    help="the live job's final run (spadscan worker --live --budget-s; default: the live default)")
    ap.add_argument("--offline-budget-s", type=float, default=None,
                    help="the offline job's budget (spadscan worker --budget-s; default: the preset's)")
    ap.add_argument("--threads", type=int, default=None,
                    help="OMP_NUM_THREADS of the workers (default: theirs, the cores shared among their jobs)")
    ap.add_argument("--timeout-s", type=float, default=3600.0, help="longest one scan and its job may take")
    ap.add_argument("--overhead-poses", type=int, default=100,
                    help="poses of each daemon_overhead.py run on the first scene (0: skip them; default 100)")
    ap.add_argument("--out", type=Path, default=None, help="folder for captures, logs and JSON (default: a new "
                                                            "temporary folder, kept)")
    args = ap.parse_args(argv)
    scenes = [s for s in args.scenes.split(",") if s]
    from spadscan.protocol.scenes import BUILTIN_SCENES

    if not scenes:
        ap.error(f"--scenes {args.scenes!r} names no scene")
    if len(set(scenes)) < len(scenes):
        ap.error(f"--scenes {args.scenes!r} names a scene twice")
    unknown = [s for s in scenes if s not in BUILTIN_SCENES]
    if unknown:
        ap.error(f"unknown scene(s) {', '.join(unknown)} (built-in: {', '.join(BUILTIN_SCENES)})")
    from spadscan.daemon.config import ScanConfig
    from spadscan.daemon.config_keys import key_spec

    views = key_spec(ScanConfig, "views")  # the daemon's own range: a scan it would refuse is refused here
    if args.views is not None and not views.lo <= args.views <= views.hi:
        ap.error(f"--views {args.views} must be an integer in [{views.lo:g}, {views.hi:g}]")
    # Absolute: the rig.toml written under it names its folders, and a rig file's relative paths are read from its
    # own folder, so a relative --out would name them twice over.
    out = (args.out or Path(tempfile.mkdtemp(prefix="spadscan-live-bench-"))).resolve()
    out.mkdir(parents=True, exist_ok=True)
    for scene in scenes:
        if (out / scene).exists():
            ap.error(f"{out / scene} exists: give another --out")
    print(f"machine before: {machine_note()}; runs in {out}", flush=True)
    # A time limit's SIGTERM ends the runs like Ctrl-C does: the rigs' `finally`s stop their daemon and worker (on
    # SIGTERM's default, nothing would), and the scenes done still come out.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    rows = []
    try:
        for scene in scenes:
            rows.append(run_scene(scene, out, args))
            print(f"{scene}: live {rows[-1]['live_s']:.1f} s after the scan's end, Chamfer "
                  f"{fmt(rows[-1]['live']['chamfer_mm'])} mm; offline {rows[-1]['offline_s']:.1f} s, "
                  f"{fmt(rows[-1]['offline']['chamfer_mm'])} mm", flush=True)
    except KeyboardInterrupt:
        print(f"interrupted: {len(rows)} of {len(scenes)} scenes measured (runs in {out})", file=sys.stderr,
              flush=True)
        if rows:
            print(table(rows))
        return 130
    print(f"machine after: {machine_note()}")
    print(table(rows))
    met = all(r["live_s"] <= GOAL_S and (r["live"]["chamfer_mm"] or 1e9) <= (r["offline"]["chamfer_mm"] or 0) * 1.0001
              for r in rows)
    print(f"goal: final mesh within {GOAL_S:g} s of the scan's end at a Chamfer no worse than offline: "
          f"{'met' if met else 'not met'}")
    (out / "results.json").write_text(json.dumps({"machine": machine_note(), "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
