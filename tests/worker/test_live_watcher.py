"""`spadscan worker --live`: the watcher queues a scan as a live job as soon as its first chunk is published, under
the scan's one job id (so it is queued once, live or not), and a complete scan as an ordinary job; live jobs run the
fast preset only."""

from __future__ import annotations

import json

import pytest

from spadscan.cli import main
from spadscan.protocol.errors import ConfigError
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue
from spadscan.worker.watcher import JobOptions, scan_once

from live_helpers import ReplayScan


def queued_job(queue: Queue, job_id: str) -> dict:
    return json.loads((queue.path / "queued" / f"{job_id}.json").read_text())


def test_a_running_scan_is_queued_live_at_its_first_chunk_and_once(cylinder_capture, tmp_path):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    queue = Queue.for_root(root)
    live = JobOptions(live=True)
    report = scan_once(root, queue, live)
    assert report.pending == ["cyl"] and not report.live  # running, nothing published yet
    scan.publish(1)
    assert scan_once(root, queue, JobOptions()).pending == ["cyl"]  # without --live it waits for the end
    report = scan_once(root, queue, live)
    assert report.live == ["cyl"] and not report.queued
    job = queued_job(queue, "cyl-fast")
    assert job["live"] is True and Job.from_dict(job).live
    scan.publish(23)
    scan.finish()
    assert scan_once(root, queue, live).queued == []  # the same job: never queued twice
    assert scan_once(root, queue, JobOptions()).queued == []


def test_a_complete_scan_is_an_ordinary_job_also_with_live(cylinder_capture, tmp_path):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(24)
    scan.finish()
    queue = Queue.for_root(root)
    assert scan_once(root, queue, JobOptions(live=True)).queued == ["cyl"]
    assert "live" not in queued_job(queue, "cyl-fast")  # an ordinary job's file is as it always was


def test_an_aborted_scan_is_not_queued_live(cylinder_capture, tmp_path):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(3)
    scan.finish("aborted", "stopped")
    assert scan_once(root, Queue.for_root(root), JobOptions(live=True)).skipped == ["cyl"]


def test_live_jobs_run_the_fast_preset_only():
    with pytest.raises(ConfigError, match="live reconstruction runs the 'fast' preset"):
        JobOptions(preset="paper", live=True).check()


def test_live_does_not_go_with_status(tmp_path, capsys):
    assert main(["worker", "--root", str(tmp_path), "--status", "--live"]) == 1
    assert "--live" in capsys.readouterr().err
