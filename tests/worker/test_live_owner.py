"""Two queues on one root with `--live` workers queue a scan's live job under one id each: the live folder is the
one that took it first, told from the other by the owner token its job file and its live status carry; the other
never clears, overwrites, ends, fails or queues it, and runs as an ordinary job."""

from __future__ import annotations


from spadscan.protocol.live_status import LiveStatus, read_status, write_status
from spadscan.worker.job_progress import final_run_start
from spadscan.worker.jobs import Job
from spadscan.worker.live.done import mark_live_done, mark_live_failed, mark_live_queued
from spadscan.worker.live.publish import live_folder, take_live_folder
from spadscan.worker.queue import Queue
from spadscan.worker.status_detail import live_detail

from live_helpers import ReplayScan, SecondLiveJob
from test_live_job import small_settings
from test_worker_process import options_recon


def two_queues_jobs(root) -> tuple[Job, Job]:
    """The live job mug-fast as each of two queues on `root` hands it to its worker."""
    jobs = []
    for name in (".queue", ".queue-b"):
        queue = Queue(root / name)
        assert queue.enqueue(Job(id="mug-fast", scan="mug", live=True, device="cpu"))
        jobs.append(queue.claim().job)
    return jobs[0], jobs[1]


def test_each_queue_gives_its_live_job_an_owner_of_its_own(tmp_path):
    first, second = two_queues_jobs(tmp_path)
    assert first.id == second.id and first.owner and second.owner and first.owner != second.owner
    ordinary = Queue(tmp_path / ".queue")
    assert ordinary.enqueue(Job(id="cup-fast", scan="cup"))
    assert ordinary.claim().job.owner == ""  # an ordinary job's file is as it always was
    assert "owner" not in Job(id="cup-fast", scan="cup").to_dict()


def test_the_other_queues_live_job_of_the_same_id_does_not_hold_the_folder(tmp_path):
    first, second = two_queues_jobs(tmp_path)
    folder = live_folder(tmp_path / "mug")
    start = dict(views_used=0, views_published=3, steps=0, state="waiting", job="mug-fast")
    assert take_live_folder(folder, first, LiveStatus(**start, owner=first.owner)) is None
    assert take_live_folder(folder, second, LiveStatus(**start, owner=second.owner)) == "mug-fast"
    assert read_status(folder / "status.json").owner == first.owner
    assert take_live_folder(folder, first, LiveStatus(**start, owner=first.owner)) is None  # its own retry


def test_the_other_queues_job_never_ends_fails_or_queues_the_holders_status(tmp_path):
    first, second = two_queues_jobs(tmp_path)
    folder = live_folder(tmp_path / "mug")
    write_status(folder, LiveStatus(views_used=40, views_published=48, steps=900, state="live", job="mug-fast",
                                    owner=first.owner))
    before = (folder / "status.json").read_bytes()
    (result := tmp_path / "mug" / "recon" / "mug-fast").mkdir()
    mark_live_failed(second, tmp_path, "its final run crashed", print)
    mark_live_queued(second, tmp_path, "its worker was stopped", print)
    mark_live_done(second, tmp_path, result, print)
    assert (folder / "status.json").read_bytes() == before
    mark_live_done(first, tmp_path, result, print)
    status = read_status(folder / "status.json")
    assert (status.state, status.owner, status.result) == ("done", first.owner, str(result))


def test_the_other_queues_live_job_runs_as_an_ordinary_job_leaving_the_folder_alone(cylinder_capture, tmp_path):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "mug")
    scan.publish(3)
    first, second = two_queues_jobs(root)
    folder = live_folder(root / "mug")
    write_status(folder, LiveStatus(views_used=40, views_published=48, steps=900, state="live", job="mug-fast",
                                    owner=first.owner, chamfer_mm=2.5))
    (folder / "mesh.ply").write_text("the holder's mesh")
    before = (folder / "status.json").read_bytes()
    run = SecondLiveJob(second, root, root / "mug" / "recon" / ".tmp-b", "another queue's live job mug-fast",
                        recon=options_recon, settings=small_settings())
    assert run.after_scan(scan)["device"] == "cpu"  # the ordinary job's report
    assert (folder / "status.json").read_bytes() == before
    assert (folder / "mesh.ply").read_text() == "the holder's mesh"


def test_a_row_or_claim_of_the_other_queues_job_never_shows_the_holders_progress(tmp_path):
    """The other queue's job of the same id runs as an ordinary job once the scan has ended, while the holder may
    still be in its final run: `--status` and the worker's progress line must not give it the holder's figures."""
    first, second = two_queues_jobs(tmp_path)
    folder = live_folder(tmp_path / "mug")
    write_status(folder, LiveStatus(views_used=40, views_published=48, steps=900, state="final", job="mug-fast",
                                    owner=first.owner))
    rows = {}
    for name in (".queue", ".queue-b"):
        [row] = [r for r in Queue(tmp_path / name).statuses() if r.id == "mug-fast"]
        rows[name] = row
    assert rows[".queue"].owner == first.owner and rows[".queue-b"].owner == second.owner
    assert live_detail(tmp_path, rows[".queue"]).startswith("live reconstruction finishing")
    assert live_detail(tmp_path, rows[".queue-b"]) is None
    assert final_run_start(tmp_path, first) is not None and final_run_start(tmp_path, second) is None
    earlier = Job(id="mug-fast", scan="mug", live=True)  # a job file of an earlier version: no owner token
    assert final_run_start(tmp_path, earlier) is not None
