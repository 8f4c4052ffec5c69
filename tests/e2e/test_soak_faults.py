"""A soak under faults: one daemon and two workers on simulated devices, for about two minutes, while the daemon and
each worker are killed (kill -9) at random moments (seeded), the simulated arm makes protective stops and the
simulated sensor falls silent. At the end every scan is complete with every pose once and every job has exactly one
result. The counts of faults injected and survived are printed.

Each daemon is started with auto_resume (a restarted daemon resumes the interrupted scan by itself) and a fresh,
seeded schedule of faults (`protective_stop_on_move`, `silence_on_frames`); the test resumes every pause, as an
operator would (after a silence, once the sensor speaks again). The workers run a stand-in reconstruction
(soak_stand_in.py) that checks its capture and takes a second or so, so that kills land in jobs and in publishing.
"""

from __future__ import annotations

import collections
import json
import os
import random
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from e2e_helpers import assert_every_pose_once
from spadscan.daemon.client import ControlError, call
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.worker.jobs import COMPLETE
from spadscan.worker.queue import Queue

SEED = int(os.environ.get("SPADSCAN_SOAK_SEED", "35"))
SCANS = [f"soak{i}" for i in range(16)]
VIEWS, FRAMES = 20, 2
SCAN = {"views": VIEWS, "frames_per_pose": FRAMES, "chunk_size": FRAMES}
DAEMON_KILLS, WORKER_KILLS = 8, 18
"""Kills to inject; then the faults stop and everything must come to its end."""
JOB_KILLS = 2
IDLE_KILLS = 6
"""Kills of idle workers, at most: the rest wait until the worker holds a job, so that kills land in jobs however
slowly the scans (and so the jobs) come on a busy machine."""
"""Kills of workers while they hold one job, at most: a job whose worker keeps dying fails after its attempts
(max_attempts 5 in WORKER: a job's attempt may also end when a worker is killed just as it claims the job)."""
IDLE = "(no job)"
END_S = 300.0
"""How long everything may take to finish (it takes about two minutes on two busy cores)."""

WORKER = """
import asyncio, sys
from spadscan.worker.pool import run_worker
from spadscan.worker.worker_config import WorkerConfig
config = WorkerConfig(root=sys.argv[1], processes=1, poll_s=0.2, lease_s=10.0, max_attempts=5,
                      recon="soak_stand_in:reconstruct", stop_grace_s=5)
asyncio.run(run_worker(config))
"""


@dataclass
class Faults:
    """Faults injected, each with what it hit: {kind: [scan or job]}."""

    hit: dict[str, list[str]] = field(default_factory=lambda: collections.defaultdict(list))

    def add(self, kind: str, target: str) -> None:
        self.hit[kind].append(target)


class Soak:
    def __init__(self, tmp_path: Path, procs, make_daemon, seed: int):
        self.root = tmp_path / "caps"
        self.root.mkdir()
        self.procs, self.make_daemon = procs, make_daemon
        # Two streams: the daemon's faults are drawn in the order of its scans and restarts, the workers' as jobs
        # appear, so that the one does not shift the other.
        self.rng, self.worker_rng = random.Random(seed), random.Random(seed + 1)
        self.faults = Faults()
        self.daemons = 0
        self.daemon = None
        self.paused_here = 0
        """Pauses of the current daemon: it is killed only after its own stop and silence, so that each shows."""
        self.kill_at: dict[str, int | None] = {}
        self.pause: tuple | None = None
        self.kill_worker_at = [0.0, 0.0]
        self.workers = [self.start_worker(i) for i in range(2)]

    # ---- the daemon ---------------------------------------------------------------------------------------------
    def start_daemon(self) -> None:
        """A daemon with a fresh fault schedule: one protective stop and one silence within its first scans."""
        self.daemons += 1
        self.paused_here = 0
        arm = {"motion_time_s": 0.08, "protective_stop_on_move": [self.rng.randint(2, VIEWS)]}
        sensor = {"rays_per_zone": 2, "frame_timeout_s": 1.0, "silence_s": 2.0,
                  "silence_on_frames": [self.rng.randint(2, VIEWS * FRAMES)]}
        self.daemon = self.make_daemon(captures=self.root, name=f"rig{self.daemons}", arm=arm, sensor=sensor,
                                       scan=SCAN, top={"auto_resume": True}).start()

    def step_daemon(self, faults_on: bool) -> None:
        try:
            status = self.daemon.status()
        except ControlError:
            return  # busy restarting a scan; asked again next time
        state, scan = status["state"], status.get("scan")
        if state == "paused":
            self.on_pause(status)
        elif state == "idle":
            self.pause = None
            name = next((s for s in SCANS if not self.started(s)), None)
            if name is not None:
                self.kill_at[name] = (self.rng.randint(2, VIEWS - 3)
                                      if faults_on and self.rng.random() < 0.75 else None)
                try:
                    self.daemon.call("scan", name=name)
                except ControlError:
                    pass  # asked again next time
        elif state == "scanning" and faults_on and self.kill_at.get(scan) is not None \
                and (status.get("pose") or 0) >= self.kill_at[scan] and self.paused_here >= 2 \
                and len(self.faults.hit["daemon kill -9"]) < DAEMON_KILLS:
            self.kill_at[scan] = None
            self.daemon.kill9()
            self.faults.add("daemon kill -9", scan)
            self.start_daemon()

    def on_pause(self, status: dict) -> None:
        reason, scan = status.get("reason") or "", status["scan"]
        episode = (self.daemons, scan, status.get("pose"), reason)
        if self.pause != episode:
            self.pause = episode
            kind = ("protective stop" if "protective stop" in reason else
                    "sensor silence" if "sensor silent" in reason else "other pause")
            self.faults.add(kind, scan)
            self.paused_here += 1
        if status["sensor"].get("silent"):
            return  # resumed once the sensor speaks again
        try:
            self.daemon.call("resume")
        except ControlError:
            pass  # it changed state meanwhile

    def started(self, name: str) -> bool:
        return (self.root / name / "scan.json").is_file()

    def complete(self, name: str) -> bool:
        try:
            return CaptureReader(self.root / name).state == "complete"
        except Exception:  # noqa: BLE001 - not there yet
            return False

    # ---- the workers --------------------------------------------------------------------------------------------
    def start_worker(self, i: int):
        here = str(Path(__file__).resolve().parent)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([here, os.environ.get("PYTHONPATH", "")])}
        self.kill_worker_at[i] = time.monotonic() + self.worker_rng.uniform(0.5, 4.0)
        return self.procs.start([sys.executable, "-c", WORKER, str(self.root)], f"worker{i}", env=env)

    def step_workers(self, faults_on: bool) -> None:
        """Kill each worker at random moments (a draw of 0.5-4 s after it was started), whatever it is doing; but
        an idle worker is hit at most IDLE_KILLS times, and a job at most JOB_KILLS times, so that it can still end
        within its attempts."""
        now = time.monotonic()
        for i, worker in enumerate(self.workers):
            if not faults_on or len(self.faults.hit["worker kill -9"]) >= WORKER_KILLS or now < self.kill_worker_at[i]:
                continue
            jobs = self.held_by(worker.pid)
            if not jobs and self.faults.hit["worker kill -9"].count(IDLE) >= IDLE_KILLS:
                continue
            if any(self.faults.hit["worker kill -9"].count(job) >= JOB_KILLS for job in jobs):
                continue
            worker.kill()
            worker.wait(timeout=30)
            self.faults.add("worker kill -9", jobs[0] if jobs else IDLE)
            self.workers[i] = self.start_worker(i)

    def held_by(self, pid: int) -> list[str]:
        """The jobs a worker holds (claimed, not yet settled: starting, running or publishing)."""
        queue = Queue.for_root(self.root, create=False)
        held = []
        for job_id, (state, path) in queue.job_paths().items():
            if state == "running" and (queue.record(job_id, path.stem.rpartition("~")[2]) or {}).get("pid") == pid:
                held.append(job_id)
        return held

    # ---- the end ------------------------------------------------------------------------------------------------
    def describe(self) -> str:
        """Where things stand, for a soak that did not finish."""
        try:
            status = call(self.daemon.sock, "status", timeout_s=5)
        except ControlError as exc:
            status = f"no answer ({exc})"
        unfinished = [s for s in SCANS if not self.complete(s)]
        rows = [(r.id, r.shown_state, r.attempts, r.error) for r in Queue.for_root(self.root).statuses()
                if r.state != "done"]
        return (f"faults {dict(self.faults.hit)}; scans not complete {unfinished}; jobs not done {rows}; daemon "
                f"status {status}; daemon log ...{self.daemon.log()[-2000:]}")

    def finished(self) -> bool:
        if not all(self.complete(s) for s in SCANS):
            return False
        counts = Queue.for_root(self.root, create=False).counts()
        if (counts["done"], counts["queued"], counts["running"]) != (len(SCANS), 0, 0):
            return False
        return not any(p.name.startswith(".") for s in SCANS for p in (self.root / s / "recon").iterdir())


@pytest.mark.slow
def test_soak_kill_9_stops_and_silences_every_scan_complete_every_job_one_result(tmp_path, procs, make_daemon,
                                                                                  capsys):
    soak = Soak(tmp_path, procs, make_daemon, SEED)
    soak.start_daemon()
    t0 = time.monotonic()
    deadline = t0 + END_S
    while not soak.finished():
        assert time.monotonic() < deadline, f"not finished after {END_S:g} s: {soak.describe()}"
        faults_on = (len(soak.faults.hit["daemon kill -9"]) < DAEMON_KILLS
                     or len(soak.faults.hit["worker kill -9"]) < WORKER_KILLS) and time.monotonic() - t0 < 150
        soak.step_daemon(faults_on)
        soak.step_workers(faults_on)
        time.sleep(0.05)
    elapsed = time.monotonic() - t0

    queue = Queue.for_root(soak.root)
    for name in SCANS:
        assert_every_pose_once(soak.root / name, VIEWS, FRAMES)
        job = f"{name}-fast"
        recon = soak.root / name / "recon"
        assert [p.name for p in recon.iterdir()] == [job], f"{job}: one result, nothing beside it"
        assert {"mesh.ply", "report.json", "job.log", COMPLETE} <= {p.name for p in (recon / job).iterdir()}
        assert json.loads((recon / job / "report.json").read_text())["measurements"] == VIEWS * FRAMES
        outcomes = [r.get("outcome") for r in queue.records(job)]
        assert outcomes.count("done") == 1, f"{job}: {outcomes}"
    rows = {r.id: r for r in queue.statuses()}
    assert {r.state for r in rows.values()} == {"done"} and all(r.result for r in rows.values())
    assert soak.daemon.stop() == 0, soak.daemon.log()
    for worker in soak.workers:
        assert procs.stop(worker) == 0, procs.log(worker)

    hit = soak.faults.hit
    survived = {kind: sum(1 for t in targets if (soak.complete(t) if not kind.startswith("worker") else
                                                  t == IDLE or rows[t].state == "done"))
                for kind, targets in hit.items()}
    with capsys.disabled():
        print(f"\nsoak (seed {SEED}, {elapsed:.0f} s): faults injected "
              + ", ".join(f"{kind} x{len(t)}" for kind, t in sorted(hit.items()))
              + f" ({sum(t != IDLE for t in hit['worker kill -9'])} of them while the worker held a job, "
              f"{len(set(hit['worker kill -9']) - {IDLE})} jobs hit)"
              + "; survived " + ", ".join(f"{kind} x{n}" for kind, n in sorted(survived.items()))
              + f"; {len(SCANS)} scans complete with every pose once, {len(SCANS)} jobs with one result each")
    assert len(hit["daemon kill -9"]) >= 1 and set(hit["worker kill -9"]) - {IDLE}, "kills mid-scan and mid-job"
    assert hit["protective stop"] and hit["sensor silence"], dict(hit)
    assert survived == {kind: len(t) for kind, t in hit.items()}
