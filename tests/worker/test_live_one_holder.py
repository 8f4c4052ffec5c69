"""`<scan>/recon/live/` is one live job's: a second live job of the scan (another preset, a hashed id) never clears,
ends, fails or finishes it, and runs as an ordinary job; a live job re-run after its scan was aborted keeps the last
live result and says 'aborted'; --redo and --retry-failed say 'queued' in the live status of the job they queue."""

from __future__ import annotations

import json

import pytest

from spadscan.cli import main as cli_main
from spadscan.protocol.live_status import LiveStatus, read_status, status_path, write_status
from spadscan.worker.jobs import Job
from spadscan.worker.live.done import mark_live_done, mark_live_failed
from spadscan.worker.live.job import ScanAborted, execute_live_job
from spadscan.worker.live.publish import clear_earlier, live_folder, take_live_folder
from spadscan.worker.queue import Queue

from live_helpers import ReplayScan, SecondLiveJob
from test_live_job import small_settings
from test_worker_process import options_recon

FAST_STATUS = dict(views_used=40, views_published=48, steps=900, state="live", job="mug-fast", chamfer_mm=2.5)


def holder_folder(root):
    """A scan whose live folder the live job mug-fast holds, following the scan, with its mesh."""
    folder = live_folder(root / "mug")
    write_status(folder, LiveStatus(**FAST_STATUS))
    (folder / "mesh.ply").write_text("fast's mesh")
    return folder


def test_another_live_jobs_end_leaves_the_holders_status_alone(tmp_path):
    folder = holder_folder(tmp_path)
    paper = Job(id="mug-paper", scan="mug", preset="paper", live=True)
    mark_live_failed(paper, tmp_path, "paper's final run crashed", print)
    assert read_status(folder / "status.json").state == "live"
    (result := tmp_path / "mug" / "recon" / "mug-paper").mkdir()
    mark_live_done(paper, tmp_path, result, print)
    status = read_status(folder / "status.json")
    assert (status.state, status.job, status.result) == ("live", "mug-fast", None)
    fast = Job(id="mug-fast", scan="mug", live=True)
    mark_live_done(fast, tmp_path, result, print)
    status = read_status(folder / "status.json")
    assert (status.state, status.job, status.result) == ("done", "mug-fast", str(result))


def test_the_first_live_job_takes_the_folder_and_a_second_one_is_told_whose_it_is(tmp_path):
    folder = live_folder(tmp_path / "mug")
    first = LiveStatus(views_used=0, views_published=3, steps=0, state="waiting", job="mug-fast")
    assert take_live_folder(folder, Job(id="mug-fast", scan="mug", live=True), first) is None
    assert read_status(folder / "status.json").job == "mug-fast"
    other = LiveStatus(views_used=0, views_published=3, steps=0, state="waiting", job="mug-paper")
    assert take_live_folder(folder, Job(id="mug-paper", scan="mug", live=True), other) == "mug-fast"
    assert take_live_folder(folder, Job(id="mug-fast", scan="mug", live=True), first) is None  # its own retry
    assert read_status(folder / "status.json").job == "mug-fast"
    assert sorted(p.name for p in folder.iterdir()) == ["status.json"]  # no claim left behind


def test_a_second_live_job_of_a_scan_runs_as_an_ordinary_job_and_never_touches_the_live_folder(
        cylinder_capture, tmp_path):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "mug")
    scan.publish(3)
    folder = holder_folder(root)
    before = (folder / "status.json").read_bytes()
    job = Job(id="mug-paper", scan="mug", preset="paper", live=True, device="cpu")
    second = SecondLiveJob(job, root, root / "mug" / "recon" / ".tmp-paper", "mug-fast's", recon=options_recon,
                           settings=small_settings())
    assert second.after_scan(scan)["device"] == "cpu"  # the ordinary job's report
    assert (folder / "status.json").read_bytes() == before
    assert (folder / "mesh.ply").read_text() == "fast's mesh"
    assert sum("publishes nothing there" in line for line in second.lines) == 1, second.lines


def test_a_rerun_after_the_scan_was_aborted_keeps_the_last_live_result(cylinder_capture, tmp_path):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(12)
    live = live_folder(root / "cyl")
    (live / "mesh.ply").write_text("the earlier attempt's last live mesh")
    (live / "preview.png").write_bytes(b"png")
    write_status(live, LiveStatus(views_used=10, views_published=12, steps=300, state="queued", job="cyl-fast",
                                  chamfer_mm=1.5, note="the worker died"))
    scan.finish("aborted", "aborted by user")
    job = Job(id="cyl-fast", scan="cyl", live=True, device="cpu")
    with pytest.raises(ScanAborted, match="stays in"):
        execute_live_job(job, root, root / "cyl" / "recon" / ".tmp-x", settings=small_settings(), log=print)
    assert (live / "mesh.ply").read_text() == "the earlier attempt's last live mesh"
    assert (live / "preview.png").read_bytes() == b"png"
    status = read_status(live / "status.json")
    assert (status.state, status.job, status.views_used, status.steps, status.chamfer_mm) == (
        "aborted", "cyl-fast", 10, 300, 1.5)
    assert "aborted by user" in status.note


def test_a_killed_jobs_temporary_files_are_removed(tmp_path):
    folder = live_folder(tmp_path / "mug")
    for name in (".mesh.ply.tmp", ".status.json.123-ab12cd34.tmp", ".preview.png.ab12cd34.png"):
        (folder / name).write_text("half written")
    (folder / "mesh.ply").write_text("mesh")
    clear_earlier(folder)
    assert list(folder.iterdir()) == []


def test_a_stopped_status_labels_its_figures_the_stopped_attempts():
    status = LiveStatus(views_used=40, views_published=48, steps=900, state="stopped", job="mug-fast",
                        chamfer_mm=2.5, updated_utc="2026-12-07T07:00:00+00:00", note="crashed")
    assert "the stopped attempt's 40/48 views" in status.summary()


def queue_job(root, state: str, job: Job) -> Queue:
    """The root's queue with `job` moved to `state` (as a worker leaves a done or failed job)."""
    queue = Queue(root / ".queue")
    assert queue.enqueue(job)
    (queue.path / "queued" / f"{job.id}.json").rename(queue.path / state / f"{job.id}.json")
    return queue


@pytest.mark.parametrize("flag, state, live_state", [("--redo", "done", "done"),
                                                     ("--retry-failed", "failed", "stopped")])
def test_queueing_a_live_job_again_says_queued_in_its_live_status(tmp_path, capsys, flag, state, live_state):
    root = tmp_path
    (result := root / "mug" / "recon" / "mug-fast").mkdir(parents=True)
    (result / "report.json").write_text(json.dumps({"chamfer_mm": 1.24, "steps": 1805}))
    folder = live_folder(root / "mug")
    write_status(folder, LiveStatus(**{**FAST_STATUS, "state": live_state, "chamfer_mm": 1.24,
                                       "result": str(result) if live_state == "done" else None}))
    queue = queue_job(root, state, Job(id="mug-fast", scan="mug", live=True))
    args = ["worker", "--root", str(root), flag] + (["mug-fast"] if flag == "--redo" else [])
    assert cli_main(args) == 0, capsys.readouterr().err
    assert queue.counts()["queued"] == 1
    status = read_status(status_path(root / "mug"))
    assert (status.state, status.job, status.result) == ("queued", "mug-fast", None)
    assert flag in status.note
    assert "the stopped attempt's" in status.summary()
