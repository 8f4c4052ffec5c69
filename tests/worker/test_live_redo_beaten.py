"""`spadscan worker --redo` of a live job that another process moves out of done/ first (between this --redo's
'queued' in the live status and its own move) queues nothing: the live status must not go on saying it queued the
job, which no worker would ever replace where nothing did."""

from __future__ import annotations

import json

from spadscan.cli import main as cli_main
from spadscan.protocol.live_status import LiveStatus, read_status, status_path, write_status
from spadscan.worker.jobs import Job
from spadscan.worker.live.done import mark_live_queued
from spadscan.worker.live.publish import live_folder
from spadscan.worker.queue import Queue

DONE = dict(views_used=48, views_published=48, steps=1805, state="done", job="mug-fast", chamfer_mm=1.24)


def done_live_job(root) -> tuple[Queue, Job]:
    """The root's queue holding the done live job mug-fast, its result and its 'done' live status."""
    (result := root / "mug" / "recon" / "mug-fast").mkdir(parents=True)
    (result / "report.json").write_text(json.dumps({"chamfer_mm": 1.24, "steps": 1805}))
    queue = Queue(root / ".queue")
    assert queue.enqueue(Job(id="mug-fast", scan="mug", live=True))
    job = queue.claim().job
    (queue.path / "running").iterdir().__next__().rename(queue.path / "done" / "mug-fast.json")
    write_status(live_folder(root / "mug"), LiveStatus(**DONE, result=str(result), owner=job.owner))
    return queue, job


def beaten_by(monkeypatch, other) -> None:
    """Run `other(queue)` (another process moving the job) just before --redo moves the job itself."""
    real = Queue.requeue

    def requeue(self, state, job_id=None, **kwargs):
        other(self)
        return real(self, state, job_id, **kwargs)

    monkeypatch.setattr(Queue, "requeue", requeue)


def redo(root, capsys) -> str:
    code = cli_main(["worker", "--root", str(root), "--redo", "mug-fast"])
    err = capsys.readouterr().err
    assert code != 0 and "another process moved the job" in err, (code, err)
    return err


def test_a_redo_beaten_by_a_silent_requeue_says_another_process_queued_the_job(tmp_path, monkeypatch, capsys):
    queue, _ = done_live_job(tmp_path)
    # a worker queues a done job whose result is gone (this --redo moved it aside) before the --redo can
    beaten_by(monkeypatch, lambda q: (q.path / "done" / "mug-fast.json").rename(q.path / "queued" / "mug-fast.json"))
    redo(tmp_path, capsys)
    assert queue.counts()["queued"] == 1
    status = read_status(status_path(tmp_path / "mug"))
    assert status.state == "queued"
    assert "another process" in status.note and "--redo queued nothing" in status.note, status.note


def test_a_redo_beaten_by_another_redo_leaves_that_ones_word(tmp_path, monkeypatch, capsys):
    queue, job = done_live_job(tmp_path)

    def other_redo(q):
        mark_live_queued(job, tmp_path, "queued again by the other --redo", print, ended_too=True)
        (q.path / "done" / "mug-fast.json").rename(q.path / "queued" / "mug-fast.json")

    beaten_by(monkeypatch, other_redo)
    redo(tmp_path, capsys)
    status = read_status(status_path(tmp_path / "mug"))
    assert (status.state, status.note.split(";")[0]) == ("queued", "queued again by the other --redo")


def test_a_redo_beaten_by_a_process_that_took_the_job_away_puts_the_earlier_status_back(
        tmp_path, monkeypatch, capsys):
    queue, _ = done_live_job(tmp_path)
    before = status_path(tmp_path / "mug").read_bytes()
    beaten_by(monkeypatch, lambda q: (q.path / "done" / "mug-fast.json").unlink())  # its queue cleared by hand
    redo(tmp_path, capsys)
    assert status_path(tmp_path / "mug").read_bytes() == before
