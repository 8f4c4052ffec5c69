"""The folder watcher: every complete scan is queued once; running scans wait; aborted ones are skipped."""

from __future__ import annotations

import asyncio
import json
import shutil
import time

import numpy as np
import pytest

from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker.jobs import Job, job_id_for, old_job_id_for
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.watcher import SETTLE_S, JobOptions, scan_folders, scan_once, watch
from spadscan.worker.worker_config import WorkerConfig


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


def test_a_worker_run_once_says_when_a_copy_under_way_will_be_taken_and_that_a_recording_is_not(tmp_path, arun):
    """`worker --once` right after a copy: the scan is left, and the line says why, when it would be taken, and what
    to run; a scan still recorded is told apart from a copy."""
    complete_source(tmp_path / "s", 4)
    shutil.rmtree(sorted((tmp_path / "s").glob("chunk-*"))[-1])  # copied in so far
    make_scan(tmp_path, "rec", "running")
    q = Queue.for_root(tmp_path)
    report = scan_once(tmp_path, q, JobOptions(), now=time.time() + 20)
    assert report.pending == ["rec", "s"] and list(report.settling) == ["s"]
    assert SETTLE_S - 25 < report.settling["s"] <= SETTLE_S - 20
    lines: list[str] = []
    arun(Worker(WorkerConfig(root=tmp_path, once=True), log=lines.append).run())
    copy = [line for line in lines if "not queued: scan s " in line]
    assert len(copy) == 1 and "a copy still under way" in copy[0] and f"for {SETTLE_S:.0f} s" in copy[0], lines
    assert "run the worker again then, or without --once" in copy[0]
    recording = [line for line in lines if "not queued: scan rec " in line]
    assert len(recording) == 1 and "still being recorded" in recording[0] and "copy" not in recording[0], lines


ALIKE = ["x+y", "x_y", "mug 1", "mug_1", "tasse-\u00fc", "tasse-\u00f6"]
"""Scan names that differ only in characters outside [A-Za-z0-9._-], pair by pair."""


def test_scans_whose_names_differ_only_in_odd_characters_are_each_queued_once(tmp_path):
    for name in ALIKE:
        make_scan(tmp_path, name)
    q = Queue.for_root(tmp_path)
    assert sorted(scan_once(tmp_path, q, JobOptions()).queued) == sorted(ALIKE)
    jobs = [json.loads(p.read_text()) for p in (q.path / "queued").glob("*.json")]
    assert sorted(j["scan"] for j in jobs) == sorted(ALIKE) and len({j["id"] for j in jobs}) == len(ALIKE)
    assert {"x_y-fast", "mug_1-fast"} <= {j["id"] for j in jobs}, "safe names keep the ids they always had"
    assert scan_once(tmp_path, q, JobOptions()).queued == [], "a second pass queues nothing new"


def test_a_running_scan_with_an_odd_name_is_queued_live_under_its_own_id(tmp_path):
    make_scan(tmp_path, "x_y")
    make_scan(tmp_path, "x+y", "running")
    q = Queue.for_root(tmp_path)
    report = scan_once(tmp_path, q, JobOptions(live=True))
    assert (report.queued, report.live) == (["x_y"], ["x+y"])
    live = [j for j in q.queued_jobs() if j.live]
    assert [(j.scan, j.id) for j in live] == [("x+y", job_id_for("x+y", "fast"))]


def test_a_queue_of_old_ids_keeps_its_jobs_and_the_scan_it_hid_is_queued(tmp_path):
    """Before ids were one scan's each, `x+y` was queued as `x_y-fast`, which hid the scan `x_y`: the scans whose
    jobs that queue holds are not run again, and `x_y` gets an id of its own."""
    for name in ("x+y", "x_y", "mug 1"):
        make_scan(tmp_path, name)
    q = Queue.for_root(tmp_path)
    for name in ("x+y", "mug 1"):
        assert q.enqueue(Job(id=old_job_id_for(name, "fast"), scan=name))
    assert old_job_id_for("x+y", "fast") == "x_y-fast" and old_job_id_for("mug 1", "fast") == "mug_1-fast"
    assert scan_once(tmp_path, q, JobOptions()).queued == ["x_y"]
    queued = {j.scan: j.id for j in q.queued_jobs()}
    assert queued["x_y"] == job_id_for("x_y", "fast", hashed=True) != "x_y-fast"
    assert scan_once(tmp_path, q, JobOptions()).queued == [], "and once only"
    assert scan_once(tmp_path, Queue.for_root(tmp_path), JobOptions()).queued == [], "by any watcher"


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_worker_reconstructs_both_scans_of_names_alike(tmp_path, arun, monkeypatch):
    root, markers = tmp_path / "captures", tmp_path / "markers"
    root.mkdir()
    markers.mkdir()
    for name in ("x+y", "x_y"):
        make_scan(root, name)
    monkeypatch.setenv("MARKERS", str(markers))
    config = WorkerConfig(root=root, processes=1, once=True, poll_s=0.1, recon="test_worker_process:marker_recon")
    settled = arun(Worker(config, log=lambda line: None).run(), timeout_s=120)
    ids = {name: job_id_for(name, "fast") for name in ("x+y", "x_y")}
    assert settled == {ids["x+y"]: "done", ids["x_y"]: "done"}
    for name, job_id in ids.items():
        report = json.loads((root / name / "recon" / job_id / "report.json").read_text())
        assert report["capture"] == str(root / name)
    rows = {r.id: r.result for r in Queue.for_root(root).statuses()}
    assert rows == {job_id: str(root / name / "recon" / job_id) for name, job_id in ids.items()}


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


def test_a_fifo_where_a_capture_file_belongs_is_refused_without_blocking(tmp_path):
    """A FIFO would block a plain open until something writes to it, and with it the worker's whole look for scans
    (`--status` saying it waits for scans while none is queued, and a worker deaf to Ctrl-C): refused at once."""
    import os
    import threading

    from spadscan.protocol.capture_format import (MANIFEST, chunk_name, npy_is_whole, read_json, read_npy,
                                                  write_json_atomic)
    from spadscan.protocol.errors import CaptureError
    from spadscan.worker.watcher import holds_every_measurement

    make_scan(tmp_path, "s", n=2)
    folder = tmp_path / "s"
    write_json_atomic(folder / MANIFEST, {**read_json(folder / MANIFEST), "planned_poses": 2, "frames_per_pose": 1})
    assert holds_every_measurement(folder), "whole: the chunks are read and counted"
    chunk = folder / chunk_name(0)
    for name in ("hists.npy", "meta.json"):
        (chunk / name).unlink()
        os.mkfifo(chunk / name)
    answers = {}

    def look():
        answers["whole"] = holds_every_measurement(folder)
        answers["npy"] = npy_is_whole(chunk / "hists.npy")
        try:
            read_json(chunk / "meta.json")
        except CaptureError as exc:
            answers["json"] = str(exc)
        try:
            read_npy(chunk / "hists.npy")
        except CaptureError as exc:
            answers["read"] = str(exc)

    looking = threading.Thread(target=look, daemon=True)
    looking.start()
    looking.join(timeout=30)
    assert not looking.is_alive(), "blocked on a FIFO"
    assert answers["whole"] is False and answers["npy"] is False, answers
    assert "not a regular file" in answers["json"] and "not a regular file" in answers["read"], answers
