"""Live jobs end to end: a real daemon (sim arm and sensor) scans while `spadscan worker --live` reconstructs. The
scan is paused half way (an event, not a wait on the clock) so that the live job has views to fit while the scan is
still running; `spadscan ctl status` shows the live state; a live job killed with kill -9 is taken over like any
other job and finishes the scan; an aborted scan's live job ends, failed with the scan's reason, not retried."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest

from e2e_helpers import processes_mentioning, spadscan_argv, wait_for
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.live_status import read_status, status_path
from spadscan.worker.queue import Queue

VIEWS = 16
SLOW_S = 300.0  # a fit on a busy machine may take minutes; every wait below ends as soon as its event happens
RIG = {"arm": {"motion_time_s": 0.2}, "sensor": {"rays_per_zone": 64}, "scan": {"views": VIEWS}}


def live(capture: Path):
    try:
        return read_status(status_path(capture))
    except CaptureError:
        return None


def job_pids(root: Path) -> set[int]:
    return {pid for pid, cmd in processes_mentioning(str(root)).items() if "spadscan.worker.jobs" in cmd}


def start_half_scan(make_daemon, procs, name: str):
    """A daemon scanning `name`, paused once at least half its views are published, and a live worker on its
    captures root. Returns (daemon, worker process, capture folder, first live status with a fit)."""
    daemon = make_daemon(**RIG).start()
    worker = procs.start(spadscan_argv("worker", "--root", daemon.captures, "--live", "--steps", 2, "--device", "cpu",
                                       "--poll-s", 0.2), "worker")
    daemon.call("scan", name=name, options={})
    daemon.wait_pose(name, VIEWS // 2)
    daemon.call("pause")
    daemon.wait_state("paused")
    capture = daemon.captures / name
    fitted = wait_for(lambda: (s := live(capture)) is not None and s.state == "live" and s.steps > 0 and s,
                      "a live fit", SLOW_S, poll_s=0.1)
    return daemon, worker, capture, fitted


@pytest.mark.slow
def test_a_killed_live_job_is_taken_over_and_finishes_the_scan(make_daemon, procs):
    daemon, worker, capture, fitted = start_half_scan(make_daemon, procs, "ball")
    assert VIEWS // 2 <= fitted.views_used <= fitted.views_published < VIEWS
    assert fitted.views_planned == VIEWS and fitted.chamfer_mm is not None  # the sim sensor's scene is known
    assert {"mesh.ply", "preview.png", "status.json"} <= {p.name for p in (capture / "recon" / "live").iterdir()}

    shown = json.loads(daemon.ctl("status").stdout)["live"]
    assert shown["views_used"] >= VIEWS // 2 and shown["job"] == "ball-fast" and shown["age_s"] >= 0

    queue = Queue.for_root(daemon.captures, create=False)
    (pid,) = job_pids(daemon.captures)
    os.kill(pid, signal.SIGKILL)
    wait_for(lambda: any(r.get("outcome") == "crashed" for r in queue.records("ball-fast")), "the crash recorded",
             60.0)
    wait_for(lambda: (pids := job_pids(daemon.captures)) and pid not in pids, "a new job process", 60.0)
    again = wait_for(lambda: (s := live(capture)) is not None and s.updated_utc > fitted.updated_utc
                     and s.state == "live" and s.steps > 0 and s, "the taken-over live fit", SLOW_S, poll_s=0.1)
    assert again.views_used >= fitted.views_used

    daemon.call("resume")
    wait_for(lambda: (daemon.status().get("last_scan") or {}).get("state") == "complete", "the scan complete", 120.0)
    # The queue moves the job to done/ and then records the attempt's outcome; the live status says done after both.
    wait_for(lambda: [r.get("outcome") for r in queue.records("ball-fast")][-1:] == ["done"], "the job done",
             SLOW_S, poll_s=0.2)
    wait_for(lambda: (s := live(capture)) is not None and s.state == "done", "the live status done", 60.0)
    assert queue.job_paths()["ball-fast"][0] == "done"
    records = queue.records("ball-fast")
    assert [r["outcome"] for r in records] == ["crashed", "done"]
    assert "SIGKILL" in records[0]["error"]
    result = capture / "recon" / "ball-fast"
    report = json.loads((result / "report.json").read_text())
    # The final run fits every view, starting from the live fit of the views there were before the scan ended.
    assert again.views_used <= report["live"]["views_used"] <= VIEWS and report["scene"]["views"] == VIEWS
    done = live(capture)
    assert done.state == "done" and done.result == str(result) and done.views_published == VIEWS
    # Its figures are the published result's, not the live fit's at the scan's end.
    assert done.views_used == VIEWS and done.converged == report["converged"]
    assert done.chamfer_mm == report["chamfer_mm"]
    if report["live"]["final_start"] == "hull":  # the live fit's steps shaped nothing of this result
        assert done.steps == report["steps"]
    else:
        assert done.steps >= report["live"]["steps"] + report["steps"]
    assert worker.poll() is None


@pytest.mark.slow
def test_an_aborted_scans_live_job_ends_with_the_reason_and_is_not_retried(make_daemon, procs):
    daemon, worker, capture, fitted = start_half_scan(make_daemon, procs, "cup")
    daemon.call("abort", reason="the object fell over")
    queue = Queue.for_root(daemon.captures, create=False)
    # the job file is moved to failed/ first, then its attempt record says so: wait for both
    wait_for(lambda: queue.job_paths().get("cup-fast", ("?",))[0] == "failed"
             and [r.get("outcome") for r in queue.records("cup-fast")][-1:] == ["failed"], "the job failed", SLOW_S,
             poll_s=0.2)
    (record,) = queue.records("cup-fast")
    assert record["outcome"] == "failed" and not record["retried"]
    assert "aborted" in record["error"] and "the object fell over" in record["error"]
    status = live(capture)
    assert status.state == "aborted" and "the object fell over" in status.note and status.steps >= fitted.steps
    wait_for(lambda: not job_pids(daemon.captures), "the job process gone", 60.0)
    assert worker.poll() is None and daemon.status()["state"] == "idle"
