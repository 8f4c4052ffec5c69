"""A live job back in the queue before it ended says so in its live status (`queued`, "queued again"), not
"finishing" with no process running it: when its worker is stopped (SIGTERM gives the job back) and when its process
crashed and it is retried. A job run again from scratch shows nothing of the attempt it replaces: not its figures,
not its mesh or preview.

The workers here are processes running the stand-in reconstruction `marker_recon` (test_worker_process), so that a
live job of a complete scan (reconstructed from scratch) holds its process as long as the test needs."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from spadscan.protocol.errors import CaptureError
from spadscan.protocol.live_status import SAID, LiveStatus, read_status, status_path, write_status
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue
from spadscan.worker.status_detail import live_detail

from test_watcher import make_scan
from test_worker_process import HERE, RECON, markers_of, wait_for

JOB = "s-fast"
EARLIER = LiveStatus(views_used=38, views_published=60, steps=563, state="final", chamfer_mm=68.6505,
                     updated_utc="2026-12-03T13:17:00.000+00:00", views_planned=60, job=JOB,
                     note="the earlier attempt's")
"""What a stopped attempt left: a live fit of 38 views, 563 steps, 68.65 mm."""

LAUNCH = """
import asyncio, sys
from spadscan.worker.pool import run_worker
from spadscan.worker.worker_config import WorkerConfig
config = WorkerConfig(root=sys.argv[1], processes=1, poll_s=float(sys.argv[2]), lease_s=60.0, max_attempts=3,
                      recon=%r, stop_grace_s=5)
asyncio.run(run_worker(config))
""" % RECON


@pytest.fixture
def root(tmp_path):
    """A complete scan `s`, its live job queued, and what an earlier attempt of that job left in recon/live/."""
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    live = root / "s" / "recon" / "live"
    live.mkdir(parents=True)
    write_status(live, EARLIER)
    (live / "mesh.ply").write_text("the earlier attempt's mesh")
    (live / "preview.png").write_bytes(b"\x89PNG the earlier attempt's preview")
    Queue.for_root(root).enqueue(Job(id=JOB, scan="s", live=True))
    return root


@pytest.fixture
def markers(tmp_path):
    path = tmp_path / "markers"
    path.mkdir()
    return path


def start_worker(root: Path, markers: Path, poll_s: float, **env) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")]),
           "MARKERS": str(markers), **env}
    return subprocess.Popen([sys.executable, "-c", LAUNCH, str(root), str(poll_s)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def stop(worker: subprocess.Popen) -> str:
    """SIGTERM the worker and return its log (killed, should it not stop)."""
    try:
        worker.send_signal(signal.SIGTERM)
        return worker.communicate(timeout=60)[0]
    finally:
        if worker.poll() is None:
            worker.kill()
            worker.communicate()


def live(root) -> LiveStatus | None:
    try:
        return read_status(status_path(root / "s"))
    except CaptureError:  # between writes there is always a whole file; None only if it were gone
        return None


def test_a_stopped_workers_live_job_says_queued_again_and_its_rerun_shows_nothing_of_the_earlier_attempt(
        root, markers, tmp_path):
    release = tmp_path / "release"  # never made: the stand-in holds the job until its worker stops it
    worker = start_worker(root, markers, 0.1, RELEASE=str(release))
    try:
        wait_for(lambda: markers_of(markers, "s", "start"))  # the job's final run (from scratch) has started
        rerun = live(root)
        assert (rerun.state, rerun.views_used, rerun.steps, rerun.chamfer_mm, rerun.job) == ("final", 0, 0, None, JOB)
        assert "from scratch" in rerun.note
        assert not (root / "s" / "recon" / "live" / "mesh.ply").exists(), "the earlier attempt's mesh"
        assert not (root / "s" / "recon" / "live" / "preview.png").exists(), "the earlier attempt's preview"
    finally:
        log = stop(worker)
    assert "s-fast stopped; back in the queue" in log, log
    assert Queue.for_root(root).job_paths()[JOB][0] == "queued"
    status = live(root)
    assert status.state == "queued" and SAID[status.state] == "queued again", (status, log)
    assert "worker was stopped" in status.note and "back in the queue" in status.note
    assert status.summary().startswith("live reconstruction queued again: 0/2 views, 0 steps")


def test_a_live_job_whose_process_crashed_says_queued_again_until_it_is_retried(root, markers):
    worker = start_worker(root, markers, 600.0, RECON_FAIL="s")  # its next poll, which retries it, comes late
    try:
        wait_for(lambda: (live(root) or EARLIER).state == "queued")
        status = live(root)
        assert "process crashed" in status.note and "simulated crash" in status.note, status.note
        # The status is written while the worker still holds the job (`_say_queued`), the rename to queued/ follows.
        wait_for(lambda: Queue.for_root(root).job_paths()[JOB][0] == "queued")
    finally:
        log = stop(worker)
    assert "queued again" in log, log


def test_a_status_that_says_how_the_job_ended_or_is_another_jobs_is_left_alone(tmp_path):
    from spadscan.worker.live.done import mark_live_queued

    root = tmp_path / "captures"
    (root / "s" / "recon" / "live").mkdir(parents=True)
    lines: list[str] = []
    job = Job(id=JOB, scan="s", live=True)
    mark_live_queued(job, root, "why", lines.append)  # none written yet: nothing to say, no complaint
    assert not status_path(root / "s").exists() and lines == []
    for said in (dataclasses.replace(EARLIER, state="done", result="r"), dataclasses.replace(EARLIER, job="s-paper")):
        write_status(root / "s" / "recon" / "live", said)
        mark_live_queued(job, root, "why", lines.append)
        assert live(root) == said
    assert lines == []



def test_worker_status_shows_no_given_back_attempts_line_for_the_attempt_that_took_the_job_again(tmp_path):
    """Between a worker taking the job again and its attempt writing the first status, the status still says
    'queued' (the given-back attempt's): `worker --status`'s running row leaves it out rather than say a running job
    is queued."""
    root = tmp_path / "captures"
    folder = root / "s" / "recon" / "live"
    folder.mkdir(parents=True)
    row = SimpleNamespace(state="running", id=JOB, scan="s")
    write_status(folder, dataclasses.replace(EARLIER, state="queued", note="its worker was stopped"))
    assert live_detail(root, row) is None
    write_status(folder, dataclasses.replace(EARLIER, state="live"))
    assert live_detail(root, row).startswith("live reconstruction following the scan")
