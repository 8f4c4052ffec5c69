"""A live job whose scan's live folder another live job holds (another queue's job of its id, another preset) holds
no worker while the scan is recorded: it waits in the queue, `--status` says why, and once the scan has ended it is
claimed as the ordinary job it then is, so that its budget and the worker's overdue stop apply to it as to any
ordinary job (a live job's count from its own live status's 'final', which it never writes)."""

from __future__ import annotations

import json

from spadscan.cli import main as cli_main
from spadscan.protocol.live_status import LiveStatus, read_status, status_path, write_status
from spadscan.worker.jobs import Job
from spadscan.worker.live.publish import live_folder, take_live_folder
from spadscan.worker.queue import Queue


def scan_in_state(root, state: str) -> None:
    scan = root / "mug"
    scan.mkdir(exist_ok=True)
    (scan / "scan.json").write_text(json.dumps({"state": state}))


def held_by_the_other_queue(root) -> None:
    """mug's live folder, held by the live job mug-fast of another queue on the root (its own owner token)."""
    write_status(live_folder(root / "mug"), LiveStatus(views_used=20, views_published=24, steps=400, state="live",
                                                       job="mug-fast", owner="the-other-queues"))


def test_a_live_job_of_a_scan_another_queue_follows_waits_in_the_queue_then_runs_as_an_ordinary_job(tmp_path):
    scan_in_state(tmp_path, "running")
    held_by_the_other_queue(tmp_path)
    queue = Queue.for_root(tmp_path)
    assert queue.enqueue(Job(id="mug-fast", scan="mug", live=True))
    assert queue.enqueue(Job(id="cup-fast", scan="cup"))
    claim = queue.claim()
    assert claim.job.id == "cup-fast"  # the worker is free for other jobs meanwhile
    assert queue.claim() is None
    row = next(r for r in queue.statuses() if r.id == "mug-fast")
    assert row.state == "queued" and any("holding no worker" in n for n in row.notes), row.notes
    scan_in_state(tmp_path, "complete")
    claim = queue.claim()
    assert (claim.job.id, claim.job.live) == ("mug-fast", False)  # an ordinary job: an ordinary job's limits
    assert read_status(status_path(tmp_path / "mug")).owner == "the-other-queues"


def test_status_says_why_a_live_job_waits(tmp_path, capsys):
    scan_in_state(tmp_path, "running")
    held_by_the_other_queue(tmp_path)
    assert Queue.for_root(tmp_path).enqueue(Job(id="mug-fast", scan="mug", live=True))
    assert cli_main(["worker", "--root", str(tmp_path), "--status"]) == 0
    out = capsys.readouterr().out
    assert "holding no worker: another queue's live job of this id follows it live" in out, out


def test_of_two_queues_claiming_a_scans_live_job_one_takes_the_folder_and_the_others_waits(tmp_path):
    scan_in_state(tmp_path, "running")
    first, second = Queue(tmp_path / ".queue", root=tmp_path), Queue(tmp_path / ".queue-b", root=tmp_path)
    for queue in (first, second):
        assert queue.enqueue(Job(id="mug-fast", scan="mug", live=True))
    claim = first.claim()
    assert claim.job.live
    assert second.claim() is None  # before the first one's process could take the folder
    assert not status_path(tmp_path / "mug").parent.exists()  # the job's process makes it
    folder = live_folder(tmp_path / "mug")
    start = dict(views_used=0, views_published=3, steps=0, state="waiting", job="mug-fast")
    (other,) = second.queued_jobs()  # were it claimed all the same (a worker of an earlier version)
    assert take_live_folder(folder, other, LiveStatus(**start, owner=other.owner)) == "mug-fast"
    assert take_live_folder(folder, claim.job, LiveStatus(**start, owner=claim.job.owner)) is None
    row = next(r for r in second.statuses())
    assert any("holding no worker" in n for n in row.notes), row.notes
