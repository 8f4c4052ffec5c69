"""A full disk when the queue records a failed job: the worker says so and goes on with its other jobs (it used to
end, stopping them all)."""

from __future__ import annotations

import asyncio
import errno
import os
from pathlib import Path

import pytest

from spadscan.cli import main as cli_main
from spadscan.protocol.errors import CaptureError
from spadscan.worker.pool import Worker
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue, Unrecorded
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan
from test_worker_publish_full import _starts, _until, held_recon, markers  # noqa: F401  (held_recon: the RECON below; markers: a fixture)

RECON = "test_worker_record_full:bad_or_held_recon"


def bad_or_held_recon(capture, out, **kw):
    """Scan 'bad' is refused as bad input; any other is held_recon's."""
    if Path(capture).name == "bad":
        raise CaptureError(f"{capture}: refused for the test")
    return held_recon(capture, out, **kw)


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_failure_the_full_disk_cannot_record_leaves_the_worker_and_its_other_jobs_running(
        tmp_path, arun, markers, monkeypatch, capsys):
    """The job file moves to failed/ (a rename needs no free space); its attempt record, which does, cannot be
    written: the line says where the job went and why it failed, --status says the record is missing, and the record
    is written once there is room again."""
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "bad")
    make_scan(root, "good")
    monkeypatch.setenv("HOLD", "1")
    tried = []
    full = [True]
    write_record = Queue._write_record

    def record_on_a_full_disk(self, job_id, token, rec):
        if rec.get("outcome") == "failed" and full[0]:
            tried.append(job_id)
            raise OSError(errno.ENOSPC, "No space left on device")
        return write_record(self, job_id, token, rec)

    monkeypatch.setattr(Queue, "_write_record", record_on_a_full_disk)
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, poll_s=0.05, processes=2, recon=RECON), log=lines.append)
    seen = {}

    async def main():
        stop = asyncio.Event()
        run = asyncio.create_task(worker.run(stop))
        await _until(lambda: len(tried) >= 3 or run.done())  # tried again at later polls
        assert not run.done(), "the worker ended on the full disk"
        seen["state"] = worker.queue.job_paths()["bad-fast"][0]
        assert cli_main(["worker", "--root", str(root), "--status"]) == 0
        seen["status"] = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("bad-fast"))
        full[0] = False  # room again
        await _until(lambda: "bad-fast" not in worker.unrecorded or run.done())
        await _until(lambda: _starts(markers, "good"))
        (markers / "good.go").write_text("")
        await _until(lambda: worker.settled.get("good-fast") == "done" or run.done())
        stop.set()
        await run

    arun(main())
    assert set(tried) == {"bad-fast"} and worker.settled == {"bad-fast": "failed", "good-fast": "done"}, lines
    said = [line for line in lines if line.startswith("bad-fast failed")]
    assert len(said) == 1, lines
    assert "refused for the test; moved to failed/, but its attempt record could not be written" in said[0], said
    assert "[Errno 28]" in said[0] and "taken again" not in said[0], said
    assert seen["state"] == "failed"
    assert "its last attempt record was not written" in seen["status"], seen["status"]
    assert "could write the attempt record of bad-fast again" in lines, lines
    rec = worker.queue.records("bad-fast")[-1]
    assert rec["outcome"] == "failed" and "refused for the test" in rec["error"], rec
    assert os.path.isdir(root / "good" / "recon" / "good-fast")


def test_a_crash_the_full_disk_cannot_record_says_the_job_went_back_to_the_queue(tmp_path, monkeypatch):
    queue = Queue(tmp_path / "queue")
    queue.enqueue(Job(id="s-fast", scan="s"))
    claim = queue.claim()
    write_record = Queue._write_record

    def full(self, job_id, token, rec):
        if rec.get("outcome") == "crashed":
            raise OSError(errno.ENOSPC, "No space left on device")
        return write_record(self, job_id, token, rec)

    monkeypatch.setattr(Queue, "_write_record", full)
    with pytest.raises(Unrecorded) as caught:
        queue.crash(claim, "killed by SIGKILL")
    assert caught.value.state == "queued" and queue.job_paths()["s-fast"][0] == "queued"
    assert caught.value.errno == errno.ENOSPC
    monkeypatch.setattr(Queue, "_write_record", write_record)
    queue.write_outcome(claim, caught.value.values)
    assert {k: queue.records("s-fast")[-1][k] for k in ("outcome", "error", "retried")} == {
        "outcome": "crashed", "error": "killed by SIGKILL", "retried": True}
