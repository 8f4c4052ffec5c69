"""Where a live job's time goes while its scan runs: refitting (loading the capture, carving, building the problem)
against training, under the refit rule of today beside the former one.

    python benchmarks/live_refits.py [--scene mug] [--views 128] [--every-s 0.5] [--busy N] [--out FOLDER]

A stand-in writer publishes a simulated capture of a built-in scene pose by pose, one chunk every --every-s seconds
(as the daemon does, without the arm), while a live job (one torch thread, the `fast` preset's defaults) follows it;
the job's final run gets 1 s, since only the follow phase is measured. The former rule refitted once the views grew by
a quarter or 20 s after the last refit with any new view (on a loaded machine, where a refit takes 20 s or more,
that is at every poll); today's is `live.job.refit_due`. --busy N runs N CPU-bound processes beside it (stopped at
the end) for a loaded machine. Wall-clock figures: say the machine's load with them.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.worker.jobs import Job
from spadscan.worker.live import job as live_job


def former_rule(self, progress, now: float) -> bool:
    """The refit rule before `refit_due`: a quarter more views, or 20 s since the last refit with a new view."""
    have, published = self.fit.views_used, progress.views_published
    if published < self.settings.min_views or published <= have:
        return False
    if self.fit.model is None:
        return now - self.last_rebuild >= self.settings.poll_s
    return published >= have * 1.25 or now - self.last_rebuild >= 20.0


def replay(source: Path, dest: Path, every_s: float) -> threading.Thread:
    """Publish `source`'s poses into the new capture `dest`, one chunk every `every_s`, on a thread."""
    reader = CaptureReader(source)
    data = reader.load()
    writer = CaptureWriter.create(dest, reader.sensor, schedule=reader.manifest.get("schedule"),
                                  planned_poses=reader.planned_poses(), chunk_size=1,
                                  scene=reader.manifest.get("scene"))

    def run():
        for i, meta in enumerate(data.meta):
            writer.append(Measurement(data.hists[i], data.poses[i], int(meta["pose_index"]), 0, None, {}))
            writer.flush()
            time.sleep(every_s)
        writer.finish("complete")

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def spin() -> None:
    while True:
        pass


def follow(source: Path, root: Path, name: str, every_s: float) -> dict:
    thread = replay(source, root / name, every_s)
    job = Job(id=f"{name}-fast", scan=name, live=True, budget_s=1.0, device="cpu")
    t0 = time.perf_counter()
    report = live_job.execute_live_job(job, root, root / name / "recon" / ".tmp", log=lambda line: None)
    thread.join()
    live = report["live"]
    return {"rule": name, "wall_s": round(time.perf_counter() - t0, 1), "refits": live["rebuilds"],
            "refit_s": live["rebuild_seconds"], "train_s": live["train_seconds"], "steps": live["steps"],
            "views_used": live["views_used"], "chamfer_mm": report.get("chamfer_mm")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="mug", help="built-in scene (default mug)")
    ap.add_argument("--views", type=int, default=128, help="views of the scan (default 128)")
    ap.add_argument("--every-s", type=float, default=0.5, help="seconds between chunks (default 0.5)")
    ap.add_argument("--busy", type=int, default=0, help="CPU-bound processes beside the job (default 0)")
    ap.add_argument("--out", type=Path, default=None, help="folder for the captures and refits.json (default: temp)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    out = args.out or Path(tempfile.mkdtemp(prefix="live-refits-"))
    out.mkdir(parents=True, exist_ok=True)
    source = out / "source"
    if not source.exists():
        subprocess.run([sys.executable, "-m", "spadscan.cli", "simulate", f"builtin:{args.scene}", "--out",
                        str(source), "--sensor", "tmf8820", "--views", str(args.views), "--seed", "0",
                        "--no-progress"], check=True)
    busy = [multiprocessing.Process(target=spin, daemon=True) for _ in range(args.busy)]
    for p in busy:
        p.start()
    rows = []
    try:
        today = live_job.LiveRun._refit_due
        for name, rule in (("former", former_rule), ("today", today)):
            live_job.LiveRun._refit_due = rule
            rows.append(follow(source, out, name, args.every_s))
        live_job.LiveRun._refit_due = today
    finally:
        for p in busy:
            p.terminate()
            p.join()
    print(f"{args.scene}, {args.views} views, a chunk every {args.every_s:g} s, {args.busy} busy processes, "
          f"load average {os.getloadavg()[0]:.1f}")
    print(f"{'rule':8} {'wall s':>7} {'refits':>6} {'refit s':>8} {'train s':>8} {'refit share':>11} {'steps':>6} "
          f"{'views used':>10}")
    for r in rows:
        share = r["refit_s"] / max(1e-9, r["refit_s"] + r["train_s"])
        print(f"{r['rule']:8} {r['wall_s']:7.1f} {r['refits']:6d} {r['refit_s']:8.1f} {r['train_s']:8.1f} "
              f"{share:11.0%} {r['steps']:6d} {r['views_used']:10d}")
    (out / "refits.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
