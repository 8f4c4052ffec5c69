"""`ctl status`, and `ctl wait` twice a second, read the worker's queue only as far as the scan's live job needs: a
queue's history of done jobs grows without bound (2,000 of them made each poll read 2,000 job files and records)."""

from __future__ import annotations

from spadscan.commands.ctl import live_queued
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue


def finished_jobs(root, n: int) -> Queue:
    queue = Queue.for_root(root)
    for i in range(n):
        queue.enqueue(Job(id=f"old{i}-fast", scan=f"old{i}"))
        claim = queue.claim(Holder.current())
        assert queue.finish(claim, f"recon/old{i}-fast")
    return queue


def test_no_live_job_queued_reads_no_job_statuses(tmp_path, monkeypatch):
    queue = finished_jobs(tmp_path, 5)
    read = []
    monkeypatch.setattr(Queue, "_status", lambda self, job_id, *a: read.append(job_id))
    assert live_queued(str(tmp_path), "mug") is None
    assert read == [], "no live job of the scan waits: nothing more of the queue is read"
    assert queue.counts()["done"] == 5


def test_a_waiting_live_job_reads_only_the_queued_and_running_jobs(tmp_path, monkeypatch):
    queue = finished_jobs(tmp_path, 5)
    queue.enqueue(Job(id="q1-fast", scan="q1"))
    assert queue.claim(Holder.current()).job.id == "q1-fast"
    queue.enqueue(Job(id="mug-fast", scan="mug", live=True))
    real = Queue._status
    read = []

    def counted(self, job_id, *args):
        read.append(job_id)
        return real(self, job_id, *args)

    monkeypatch.setattr(Queue, "_status", counted)
    found = live_queued(str(tmp_path), "mug")
    assert found is not None and found["job"] == "mug-fast" and found["behind"] == ["q1-fast"]
    assert sorted(read) == ["mug-fast", "q1-fast"], "the done jobs' files are not read"


def test_a_ctrl_c_as_wait_json_reads_the_ended_scans_live_status_still_prints_its_line(monkeypatch, capsys):
    import json

    from spadscan.commands import ctl

    def interrupted(capture, captures):
        raise KeyboardInterrupt

    ended = {"state": "idle", "scan": None, "daemon": {"captures": "/caps"}}
    monkeypatch.setattr(ctl, "wait_for_scan", lambda path, name, timeout, stream: {"ok": True, "name": "m",
                                                                                     "state": "complete",
                                                                                     "status": ended})
    monkeypatch.setattr(ctl, "capture_live", interrupted)
    assert ctl._wait("x.sock", "m", None, as_json=True) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1
    line = json.loads(out)
    assert line["wait"]["ended"] == "complete" and line["wait"]["name"] == "m"
    assert "state" not in line, "a status's `state` is the daemon's: with the status left out there is none"
