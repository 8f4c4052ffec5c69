"""Acquisition overhead: what the scan runner adds per pose beyond arm motion and frame time, and how many
histograms per second it streams to disk, side by side with the goals and with a peer (the bare CaptureWriter).

    python benchmarks/daemon_overhead.py [--dir FOLDER ...] [--poses N] [--frames K] [--sim-sensor]

Backends: the sim arm with zero motion time and a sensor with zero frame time. The default sensor replays frames
rendered up front by the simulator, so the figures hold only the daemon's own work (move call, frame calls, arm
state, measurement records, publishing each pose as a durable chunk: fsync + rename). `--sim-sensor` renders every
frame live instead; its render time is measured and left out as "frame time". Two more runs show what the runner
hides: publishing pose i overlaps pose i+1's move (an arm motion time) and its frames (a frame time); pose i+1 is
handed to the writer only once pose i has landed, so at most one finished pose is ever unpublished. Captures go to
a temporary folder under each --dir (default: the system temp folder and /dev/shm); the figures depend on how fast
that filesystem fsyncs, so its type is printed, and every figure stands beside the goal and the bare CaptureWriter.
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from spadscan import parent_watch
from spadscan.daemon.app import DeviceSession
from spadscan.daemon.arm.sim import SimArm
from spadscan.daemon.backends import pose_provider
from spadscan.daemon.config import config_from_dict
from spadscan.daemon.devices import Frame, Sensor
from spadscan.daemon.runner import ScanRunner
from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.scenes import builtin_scene
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, Simulator

GOAL_OVERHEAD_MS = 5.0
GOAL_HIST_PER_S = 2000.0


class ReplaySensor(Sensor):
    """Delivers pre-rendered frames at once (frame time 0): the daemon's cost without the simulator's."""

    def __init__(self, hists: np.ndarray, reference: np.ndarray | None, frame_time_s: float = 0.0):
        self.model = sensor_preset("tmf8820")
        self.name = "sensor replay"
        self.hists, self.reference, self.k, self.frame_time_s = hists, reference, 0, frame_time_s

    async def next_frame(self, timeout_s: float) -> Frame:
        i = self.k % len(self.hists)
        self.k += 1
        t0 = time.monotonic()
        if self.frame_time_s > 0:  # an exposure: the event loop is free meanwhile, as with a real sensor
            await asyncio.sleep(self.frame_time_s)
        t = time.monotonic()
        ref = None if self.reference is None else self.reference[i]
        return Frame(self.hists[i], t0, t, reference=ref, temperature_c=31.5, depths_mm=[0.0] * 36)


class Stopwatch:
    """Wraps an async method and sums the seconds spent inside it."""

    def __init__(self, obj, method: str):
        self.total = 0.0
        inner = getattr(obj, method)

        async def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return await inner(*args, **kwargs)
            finally:
                self.total += time.perf_counter() - t0

        setattr(obj, method, timed)


def make_cfg(root: Path, views: int, frames: int):
    # The scans run in this process and never open the control socket; a short path of its own keeps a deep --dir
    # within the Unix limit on socket paths that the config checks.
    socket = Path(tempfile.gettempdir()) / "spadscan-bench-unused.sock"
    return config_from_dict({
        "captures": str(root), "socket": str(socket),
        "arm": {"backend": "sim", "motion_time_s": 0.0, "hand_eye": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.05],
                                                                     [0, 0, 0, 1]]},
        "sensor": {"backend": "sim", "mesh": "builtin:sphere", "rays_per_zone": 64},
        "scan": {"views": views, "frames_per_pose": frames, "chunk_size": max(64, frames), "settle_s": 0.0,
                 "radius_m": 0.4, "target": [0, 0, 0.1]}}, root / "rig.toml")


async def run_scan(root: Path, name: str, views: int, frames: int, sensor_factory, motion_s: float = 0.0) -> dict:
    cfg = make_cfg(root, views, frames)
    arm = SimArm(motion_time_s=motion_s)
    sensor = sensor_factory(arm, cfg)
    move, frame = Stopwatch(arm, "move_to"), Stopwatch(sensor, "next_frame")
    async with DeviceSession([arm, sensor]):
        runner = ScanRunner(arm, sensor, cfg)
        try:
            await runner.start(name)
            t0 = runner.job.started
            state = (await runner.wait(name))["state"]
            wall = time.monotonic() - t0
        finally:
            await runner.shutdown()
    assert state == "complete", state
    return {"wall_s": wall, "move_s": move.total, "frame_s": frame.total, "poses": views, "hists": views * frames}


def raw_writer(root: Path, hists: np.ndarray, reference, poses: int, frames: int) -> float:
    """Peer: the bare CaptureWriter, one flush per pose, same records; returns seconds."""
    model = sensor_preset("tmf8820")
    w = CaptureWriter.create(root / "raw", model, chunk_size=max(64, frames), frames_per_pose=frames)
    pose = np.eye(4)
    meta = {"t_start": 0.0, "t_end": 0.0, "temperature_c": 31.5, "depths_mm": [0.0] * 36,
            "tcp_pose": pose.tolist(), "joints": [0.0] * 6}
    t0 = time.perf_counter()
    for i in range(poses):
        for k in range(frames):
            j = (i * frames + k) % len(hists)
            w.append(Measurement(hists[j], pose, i, k, None if reference is None else reference[j], meta))
        w.flush()
    w.finish()
    return time.perf_counter() - t0


def fs_type(path: Path) -> str:
    best, kind = "", "unknown"
    for line in Path("/proc/mounts").read_text().splitlines():
        parts = line.split()
        if len(parts) > 2 and str(path.resolve()).startswith(parts[1]) and len(parts[1]) > len(best):
            best, kind = parts[1], parts[2]
    return kind


def measure(folder: Path, args, factory, pre) -> dict:
    """Every run and its peer in a temporary folder under `folder`; figures in ms per pose and histograms per s."""
    n, k = args.poses, args.frames
    n_many = max(8, 3200 // k)
    tmp = Path(tempfile.mkdtemp(prefix="spadscan-bench-", dir=folder))  # removed in the `finally`, made just before
    try:
        one = asyncio.run(run_scan(tmp, "k1", n, 1, factory))
        moving = asyncio.run(run_scan(tmp, "moving", n, 1, factory, motion_s=args.motion_ms / 1000))
        exposing = asyncio.run(run_scan(tmp, "exposing", n, 1, lambda arm, cfg: factory(arm, cfg,
                                                                                          args.frame_ms / 1000)))
        many = asyncio.run(run_scan(tmp, "many", n_many, k, factory))
        peer_one = raw_writer(tmp / "p1", pre.hists, pre.reference, n, 1)
        peer_many = raw_writer(tmp / "pk", pre.hists, pre.reference, n_many, k)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    def overhead_ms(r):
        return (r["wall_s"] - r["move_s"] - r["frame_s"]) / r["poses"] * 1e3

    return {"fs": f"{fs_type(folder)} ({folder})", "one": overhead_ms(one), "moving": overhead_ms(moving),
            "exposing": overhead_ms(exposing), "rate": many["hists"] / (many["wall_s"] - many["move_s"] -
                                                                         many["frame_s"]),
            "peer_ms": peer_one / n * 1e3, "peer_rate": n_many * k / peer_many,
            "frame_ms": one["frame_s"] / n * 1e3, "motion_ms": moving["move_s"] / n * 1e3,
            "exposure_ms": exposing["frame_s"] / n * 1e3}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dir", action="append", default=None,
                    help="folder for the temporary captures; repeat to compare filesystems (default: the system "
                         "temp folder and /dev/shm)")
    ap.add_argument("--poses", type=int, default=100, help="poses of the per-pose overhead runs (default 100)")
    ap.add_argument("--frames", type=int, default=64, help="frames per pose of the throughput run (default 64)")
    ap.add_argument("--motion-ms", type=float, default=100.0, help="arm motion time of the hidden-publish run")
    ap.add_argument("--frame-ms", type=float, default=50.0, help="frame time of the overlapped-publish run")
    ap.add_argument("--sim-sensor", action="store_true", help="render frames live with the simulator")
    args = ap.parse_args(argv)
    if args.poses < 1 or args.frames < 1:
        ap.error(f"--poses ({args.poses}) and --frames ({args.frames}) must be >= 1")
    if not (0 <= args.motion_ms < float("inf") and 0 <= args.frame_ms < float("inf")):
        ap.error(f"--motion-ms ({args.motion_ms:g}) and --frame-ms ({args.frame_ms:g}) must be finite and >= 0")
    # Absolute, as in live.py: the rig config built under each reads its relative paths from its own folder.
    dirs = [Path(d).resolve() for d in args.dir] if args.dir else [Path(tempfile.gettempdir())] + \
        ([Path("/dev/shm")] if Path("/dev/shm").is_dir() else [])
    for d in dirs:
        if d.exists() and not d.is_dir():
            ap.error(f"--dir {d} is a file, not a folder")
        d.mkdir(parents=True, exist_ok=True)

    mesh = builtin_scene("sphere")
    model = sensor_preset("tmf8820")
    sim = Simulator(mesh, model, SimSettings(rays_per_zone=64), seed=0)
    from spadscan.protocol.schedules import fibonacci_hemisphere

    pre = sim.frames(fibonacci_hemisphere(32, 0.4, (0, 0, 0.1)))

    def replay(arm, cfg, frame_time_s=0.0):
        return ReplaySensor(pre.hists, pre.reference, frame_time_s)

    def live(arm, cfg, frame_time_s=0.0):
        from spadscan.daemon.sensor.sim import SimSensor

        return SimSensor(model, mesh, pose_provider(arm, cfg.arm.hand_eye), settings=SimSettings(rays_per_zone=64),
                         frame_time_s=frame_time_s)

    factory = live if args.sim_sensor else replay
    # Started by benchmarks/live.py, it stops when live.py is gone; a SIGTERM (that watch's, or a time limit's) ends
    # it like Ctrl-C, so that `measure` removes its temporary captures.
    parent_watch.watch_parent_from_env()
    before = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        results = [measure(d, args, factory, pre) for d in dirs]
    except KeyboardInterrupt:
        print("daemon_overhead.py: interrupted", file=sys.stderr)
        raise SystemExit(130) from None
    except SpadscanError as exc:
        raise SystemExit(f"daemon_overhead.py: error: {exc}") from None
    finally:
        signal.signal(signal.SIGTERM, before)

    k = args.frames
    rows = [("per-pose overhead, K=1, motion 0, frame time 0", f"< {GOAL_OVERHEAD_MS:g} ms",
             lambda r: f"{r['one']:.2f} ms", lambda r: f"{r['peer_ms']:.2f} ms"),
            (f"per-pose overhead, K=1, motion {args.motion_ms:g} ms", f"< {GOAL_OVERHEAD_MS:g} ms",
             lambda r: f"{r['moving']:.2f} ms", lambda r: "-"),
            (f"per-pose overhead, K=1, frame time {args.frame_ms:g} ms", f"< {GOAL_OVERHEAD_MS:g} ms",
             lambda r: f"{r['exposing']:.2f} ms", lambda r: "-"),
            (f"histograms written per s, K={k}, motion 0", f">= {GOAL_HIST_PER_S:,.0f} /s",
             lambda r: f"{r['rate']:,.0f} /s", lambda r: f"{r['peer_rate']:,.0f} /s")]
    header = ["", "goal"]
    for r in results:
        header += [f"daemon, {r['fs'].split()[0]}", f"peer, {r['fs'].split()[0]}"]
    table = [header] + [[label, goal] + [f(r) for r in results for f in (daemon, peer)]
                        for label, goal, daemon, peer in rows]
    sensor = "simulator, live (render time left out)" if args.sim_sensor else "replayed frames"
    print(f"spadscan daemon overhead: sim arm, {sensor}; {args.poses} poses per run; peer: the bare CaptureWriter "
          f"(same records, append + durable flush per pose)")
    for r in results:
        print(f"  captures on {r['fs']}: measured frame time {r['frame_ms']:.2f} ms/pose at zero, "
              f"{r['exposure_ms']:.2f} ms/pose in the frame-time run; motion {r['motion_ms']:.2f} ms/pose in the "
              f"moving run")
    widths = [max(len(row[i]) for row in table) for i in range(len(header))]
    for row in table:
        print("  " + "  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip())
    print("  Every pose is published durably (fsynced chunk + rename) before it counts, and at most one finished pose "
          "waits unpublished: at zero motion and frame time nothing is left to overlap the publish with, so its "
          "fsyncs are the floor (the peer's figure); with motion or exposure the publish runs behind them.")


if __name__ == "__main__":
    main()
