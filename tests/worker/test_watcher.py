"""The folder watcher: every complete scan is queued once; running scans wait; aborted ones are skipped."""

from __future__ import annotations

import asyncio
import json
import shutil
import time

import numpy as np

from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker.queue import Queue
from spadscan.worker.watcher import SETTLE_S, JobOptions, scan_folders, scan_once, watch


def make_scan(root, name, state="complete", n=2):
    """A tiny capture folder (n histograms of background counts) in the given state; returns its writer."""
    sensor = sensor_preset("lcspc-sim")
    rng = np.random.default_rng(0)
    w = CaptureWriter.create(root / name, sensor, chunk_size=4)
    for i in range(n):
        w.append(Measurement(rng.poisson(2.0, (1, sensor.n_bins)).astype(np.uint32), np.eye(4), i))
    if state == "running":
        w.flush()
    else:
        w.finish(state)
    return w


def test_complete_scans_are_queued_once(tmp_path):
    make_scan(tmp_path, "a")
    make_scan(tmp_path, "b", "running")
    make_scan(tmp_path, "c", "aborted")
    (tmp_path / "notes").mkdir()  # a folder without scan.json is not a scan
    q = Queue.for_root(tmp_path)
    report = scan_once(tmp_path, q, JobOptions())
    assert (report.queued, report.pending, report.skipped) == (["a"], ["b"], ["c"])
    assert [p.name for p in scan_folders(tmp_path)] == ["a", "b", "c"], "the queue folder is not a scan"
    assert scan_once(tmp_path, q, JobOptions()).queued == [], "a second pass queues nothing new"
    assert q.counts()["queued"] == 1


def test_a_scan_is_queued_when_it_completes(tmp_path):
    w = make_scan(tmp_path, "live", "running")
    q = Queue.for_root(tmp_path)
    assert scan_once(tmp_path, q, JobOptions()).queued == []
    w.finish("complete")
    assert scan_once(tmp_path, q, JobOptions()).queued == ["live"]
    job = q.claim().job
    assert (job.id, job.scan, job.preset) == ("live-fast", "live", "fast")


def test_two_watchers_on_one_root_queue_each_scan_once(tmp_path):
    for i in range(5):
        make_scan(tmp_path, f"s{i}")
    q1, q2 = Queue.for_root(tmp_path), Queue.for_root(tmp_path)
    a = scan_once(tmp_path, q1, JobOptions(preset="paper", budget_s=30.0))
    b = scan_once(tmp_path, q2, JobOptions(preset="paper", budget_s=30.0))
    assert sorted(a.queued + b.queued) == [f"s{i}" for i in range(5)]
    jobs = [json.loads(p.read_text()) for p in (q1.path / "queued").glob("*.json")]
    assert sorted(j["id"] for j in jobs) == [f"s{i}-paper" for i in range(5)]
    assert {j["budget_s"] for j in jobs} == {30.0}


def test_an_unreadable_manifest_is_queued_so_that_its_job_can_fail(tmp_path):
    """Once it has stood unchanged for SETTLE_S: before, it may be a manifest still being copied in."""
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "scan.json").write_text("{truncated")
    q = Queue.for_root(tmp_path)
    report = scan_once(tmp_path, q, JobOptions())
    assert report.pending == ["broken"] and report.unreadable == [] and not q.known("broken-fast")
    report = scan_once(tmp_path, q, JobOptions(), now=time.time() + SETTLE_S + 1)
    assert report.unreadable == ["broken"] and report.queued == []
    assert q.known("broken-fast")


def complete_source(folder, poses: int):
    """A complete capture at `folder` of `poses` poses in chunks of 2 (one measurement each)."""
    sensor = sensor_preset("lcspc-sim")
    w = CaptureWriter.create(folder, sensor, chunk_size=2, planned_poses=np.stack([np.eye(4)] * poses))
    for i in range(poses):
        w.append(Measurement(np.full((1, sensor.n_bins), 2, np.uint32), np.eye(4), i))
    w.finish("complete")


def test_a_complete_scan_still_being_copied_in_waits_for_its_chunks(tmp_path):
    """`cp -r` copies the manifest (already 'complete') before some chunks: the scan is not queued while it lacks
    measurements it plans and the copy goes on; once the last chunk lands it is queued at once."""
    source = tmp_path / "src"
    complete_source(source / "s", 6)
    root = tmp_path / "root"
    root.mkdir()
    copy = root / "s"
    copy.mkdir()
    shutil.copy2(source / "s" / "scan.json", copy)
    shutil.copy2(source / "s" / "schedule.npy", copy)
    chunks = sorted((source / "s").glob("chunk-*"))
    assert len(chunks) == 3
    q = Queue.for_root(root)
    for chunk in chunks[:2]:
        shutil.copytree(chunk, copy / chunk.name)
        assert scan_once(root, q, JobOptions()).pending == ["s"] and not q.known("s-fast")
    shutil.copytree(chunks[2], copy / chunks[2].name)
    assert scan_once(root, q, JobOptions()).queued == ["s"]


def test_a_complete_scan_whose_last_chunk_is_still_being_copied_waits_for_its_arrays(tmp_path):
    """The last chunk's meta.json has arrived (every measurement counted) but its arrays have not, or only in part:
    the job would fail for good on a missing or truncated poses.npy. It waits until they are whole."""
    source = tmp_path / "src"
    complete_source(source / "s", 4)
    root = tmp_path / "root"
    shutil.copytree(source / "s", root / "s")
    last = sorted((root / "s").glob("chunk-*"))[-1]
    (last / "poses.npy").unlink()
    hists = (last / "hists.npy").read_bytes()
    (last / "hists.npy").write_bytes(hists[:-100])
    q = Queue.for_root(root)
    assert scan_once(root, q, JobOptions()).pending == ["s"]
    (last / "hists.npy").write_bytes(hists)
    assert scan_once(root, q, JobOptions()).pending == ["s"]
    shutil.copy2(source / "s" / last.name / "poses.npy", last)
    assert scan_once(root, q, JobOptions()).queued == ["s"]


def test_a_complete_scan_short_of_measurements_is_queued_once_it_stands_still(tmp_path):
    """A copy that was cut short for good is reconstructed from what it holds (its report says so) once nothing in it
    has changed for SETTLE_S."""
    complete_source(tmp_path / "s", 4)
    shutil.rmtree(sorted((tmp_path / "s").glob("chunk-*"))[-1])
    q = Queue.for_root(tmp_path)
    assert scan_once(tmp_path, q, JobOptions()).pending == ["s"]
    assert scan_once(tmp_path, q, JobOptions(), now=time.time() + SETTLE_S + 1).queued == ["s"]


def test_watch_polls_until_stopped(tmp_path, arun):
    q = Queue.for_root(tmp_path)
    reports = []

    async def main():
        stop = asyncio.Event()
        task = asyncio.create_task(watch(tmp_path, q, JobOptions(), stop, poll_s=0.05, on_report=reports.append))
        while not reports:  # a first pass that found nothing
            await asyncio.sleep(0.01)
        make_scan(tmp_path, "late")
        deadline = time.monotonic() + 60
        while not q.known("late-fast") and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        stop.set()
        await task

    arun(main())
    assert q.known("late-fast")
    assert sum(r.queued.count("late") for r in reports) == 1
