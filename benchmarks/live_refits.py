"""Where a live job's time goes while its scan runs: refitting (loading the capture, carving, building the problem)
against training, under the refit rule of today beside the former one.

    python benchmarks/live_refits.py [--scene mug] [--views 128] [--every-s 0.5] [--busy N] [--out FOLDER]
                                     [--overwrite]

A stand-in writer publishes a simulated capture of a built-in scene pose by pose, one chunk every --every-s seconds
(as the daemon does, without the arm), while a live job (one torch thread, the `fast` preset's defaults) follows it;
the job's final run gets 1 s, since only the follow phase is measured. The former rule refitted once the views grew by
a quarter or 20 s after the last refit with any new view (on a loaded machine, where a refit takes 20 s or more,
that is at every poll); today's is `live.job.refit_due`. --busy N runs N CPU-bound processes beside it for a loaded
machine (benchmarks/contention.py's competitors: stopped at the end, and each stops by itself after a deadline or
once the benchmark is gone, so none outlives it, even killed). Wall-clock figures: say the machine's load with them.
Ctrl-C (or SIGTERM) prints the rows measured so far.

--out keeps the simulated scan in source/ (a later call with the same --scene and --views reuses it; one of another
scene or view count is refused), the replays each rule followed in former/ and today/, and refits.json. An --out that
holds former/ or today/ is refused unless --overwrite is given, which deletes them and refits.json first. A rule whose
scan completed before its live fit started has nothing to measure: its row says so, and the exit status is 1.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from contention import start_competitors, stop  # noqa: E402

from spadscan import parent_watch  # noqa: E402
from spadscan.protocol.capture_format import Measurement  # noqa: E402
from spadscan.protocol.capture_reader import CaptureReader  # noqa: E402
from spadscan.protocol.capture_writer import CaptureWriter  # noqa: E402
from spadscan.protocol.child_command import module_command  # noqa: E402
from spadscan.protocol.errors import SpadscanError  # noqa: E402
from spadscan.worker.jobs import Job  # noqa: E402
from spadscan.worker.live import job as live_job  # noqa: E402


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
                                  scene=reader.manifest.get("scene"),
                                  frames_per_pose=reader.manifest.get("frames_per_pose") or 1)

    def run():
        for i, meta in enumerate(data.meta):
            writer.append(Measurement(data.hists[i], data.poses[i], int(meta["pose_index"]), int(meta.get("frame", 0)),
                                      None, {}))
            writer.flush()
            time.sleep(every_s)
        writer.finish("complete")

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def follow(source: Path, root: Path, name: str, every_s: float) -> dict:
    thread = replay(source, root / name, every_s)
    job = Job(id=f"{name}-fast", scan=name, live=True, budget_s=1.0, device="cpu")
    t0 = time.perf_counter()
    report = live_job.execute_live_job(job, root, root / name / "recon" / ".tmp", log=lambda line: None)
    thread.join()
    live = report.get("live")
    if live is None:  # the job reconstructed the complete scan from scratch: no live phase to measure
        return {"rule": name, "wall_s": round(time.perf_counter() - t0, 1), "nothing_measured": NOT_LIVE}
    return {"rule": name, "wall_s": round(time.perf_counter() - t0, 1), "refits": live["rebuilds"],
            "refit_s": live["rebuild_seconds"], "train_s": live["train_seconds"], "steps": live["steps"],
            "views_used": live["views_used"], "chamfer_mm": report.get("chamfer_mm")}


NOT_LIVE = "the scan completed before the live fit started: nothing to measure (publish slower: a larger --every-s)"
"""A row of a rule whose live job found the scan complete before its first fit."""

SENSOR = "tmf8820"
RULES = ("former", "today")
"""The rules' replays in --out, by name."""


def source_problem(source: Path, scene: str, views: int) -> str | None:
    """Why `source`, a scan an earlier call left in --out, is not the scan this call asks for (one line), or None:
    the rows are labelled with --scene and --views, so they must be what is measured."""
    try:
        reader = CaptureReader(source)
    except SpadscanError as exc:
        return f"{source}: not a scan this script simulated ({exc}): remove it, or choose another --out"
    manifest = reader.manifest
    scene_record = manifest.get("scene") if isinstance(manifest.get("scene"), dict) else {}
    made = (scene_record.get("builtin"), manifest.get("planned_poses"), manifest["sensor"].get("name"))
    if made != (scene, views, SENSOR):
        return (f"{source}: a scan of {made[0]} with {made[1]} views ({made[2]}), not of {scene} with {views} views "
                f"({SENSOR}): choose another --out")
    if reader.state != "complete":
        return (f"{source}: its scan is {reader.state}, not complete (a simulation cut short): remove it, or choose "
                "another --out")
    return None


def out_problem(out: Path, overwrite: bool) -> str | None:
    """Why --out cannot take this call's captures (one line), or None. Reads, never writes."""
    if out.exists() and not out.is_dir():
        return f"--out {out}: exists and is not a folder"
    held = [f"{name}/" for name in RULES if (out / name).exists()]
    if held and not overwrite:
        return (f"--out {out}: already holds {', '.join(held)} of an earlier run; choose another --out, or pass "
                "--overwrite to replace them")
    return None


def clear_earlier_run(out: Path) -> None:
    """--overwrite: the replays and refits.json of an earlier run go (its source/ stays, to be reused)."""
    import shutil

    for name in RULES:
        if (out / name).is_dir() and not (out / name).is_symlink():
            shutil.rmtree(out / name)
        elif (out / name).exists() or (out / name).is_symlink():
            (out / name).unlink()
    (out / "refits.json").unlink(missing_ok=True)


def simulate(scene: str, views: int, source: Path) -> None:
    """The scan of builtin:`scene` that both rules follow; SystemExit (one line) when it cannot be made."""
    done = subprocess.run(module_command("spadscan.cli", "simulate", f"builtin:{scene}", "--out", source,
                                         "--sensor", SENSOR, "--views", views, "--seed", "0", "--no-progress"),
                          stderr=subprocess.PIPE, text=True, env=parent_watch.child_env())
    if done.returncode != 0:
        last = done.stderr.strip().splitlines()[-1:] or [f"exit status {done.returncode}"]
        raise SystemExit(f"live_refits.py: error: simulating builtin:{scene} failed: {last[0]}")


def print_rows(rows: list[dict], args) -> None:
    print(f"{args.scene}, {args.views} views, a chunk every {args.every_s:g} s, {args.busy} busy processes, "
          f"load average {os.getloadavg()[0]:.1f}")
    print(f"{'rule':8} {'wall s':>7} {'refits':>6} {'refit s':>8} {'train s':>8} {'refit share':>11} {'steps':>6} "
          f"{'views used':>10}")
    for r in rows:
        if "nothing_measured" in r:
            print(f"{r['rule']:8} {r['wall_s']:7.1f} {r['nothing_measured']}")
            continue
        share = r["refit_s"] / max(1e-9, r["refit_s"] + r["train_s"])
        print(f"{r['rule']:8} {r['wall_s']:7.1f} {r['refits']:6d} {r['refit_s']:8.1f} {r['train_s']:8.1f} "
              f"{share:11.0%} {r['steps']:6d} {r['views_used']:10d}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="mug", help="built-in scene (default mug)")
    ap.add_argument("--views", type=int, default=128, help="views of the scan (default 128)")
    ap.add_argument("--every-s", type=float, default=0.5, help="seconds between chunks, > 0 (default 0.5)")
    ap.add_argument("--busy", type=int, default=0, help="CPU-bound processes beside the job (default 0)")
    ap.add_argument("--out", type=Path, default=None, help="folder for the captures and refits.json (default: temp)")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace an earlier run's former/, today/ and refits.json in --out (its source/ is reused)")
    args = ap.parse_args(argv)
    from spadscan.protocol.scenes import BUILTIN_SCENES

    if args.scene not in BUILTIN_SCENES:
        ap.error(f"unknown scene {args.scene!r} (built-in: {', '.join(BUILTIN_SCENES)})")
    # --every-s 0 publishes the whole scan at once: it completes before any live fit, and nothing is measured.
    if args.views < 1 or args.busy < 0 or not 0 < args.every_s < float("inf"):
        ap.error("--views must be >= 1, --busy >= 0 and --every-s a finite number of seconds > 0")
    why = args.out and (out_problem(args.out, args.overwrite) or (
        source_problem(args.out / "source", args.scene, args.views) if (args.out / "source").exists() else None))
    if why:  # before anything is simulated or replayed
        ap.error(why)
    torch.set_num_threads(1)
    out = args.out or Path(tempfile.mkdtemp(prefix="live-refits-"))
    if args.overwrite:
        clear_earlier_run(out)
    out.mkdir(parents=True, exist_ok=True)
    source = out / "source"
    # A time limit's SIGTERM ends the run like Ctrl-C does: the `finally` below stops the busy processes (on SIGTERM's
    # default, nothing would), and the rows so far still come out.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    rows = []
    try:
        if not source.exists():
            simulate(args.scene, args.views, source)
        # A deadline well past both follows (each publishes the views one chunk apart, then refits and trains).
        busy = start_competitors(args.busy, deadline_s=4 * args.views * args.every_s + 600)
        today = live_job.LiveRun._refit_due
        try:
            for name, rule in (("former", former_rule), ("today", today)):
                live_job.LiveRun._refit_due = rule
                rows.append(follow(source, out, name, args.every_s))
        finally:
            live_job.LiveRun._refit_due = today
            stop(busy)
    except KeyboardInterrupt:
        print(f"interrupted: {len(rows)} of 2 rules measured", file=sys.stderr, flush=True)
        if rows:
            print_rows(rows, args)
        return 130
    except SpadscanError as exc:  # the live job or the replay failed: one line, and the rows it measured before
        print(f"live_refits.py: error: {exc}", file=sys.stderr)
        if rows:
            print_rows(rows, args)
        return 1
    print_rows(rows, args)
    (out / "refits.json").write_text(json.dumps(rows, indent=1))
    empty = [r["rule"] for r in rows if "nothing_measured" in r]
    if empty:
        print(f"live_refits.py: nothing measured for {', '.join(empty)}: {NOT_LIVE}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
