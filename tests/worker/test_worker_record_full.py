"""A full disk when the queue records a failed job: the worker says so and goes on with its other jobs (it used to
end, stopping them all)."""

from __future__ import annotations

import asyncio
import errno
import os
from pathlib import Path

import pytest

from spadscan.protocol.errors import CaptureError
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan
from test_worker_publish_full import _starts, _until, held_recon  # noqa: F401  (held_recon: the RECON below)

RECON = "test_worker_record_full:bad_or_held_recon"


def bad_or_held_recon(capture, out, **kw):
    """Scan 'bad' is refused as bad input; any other is held_recon's."""
    if Path(capture).name == "bad":
        raise CaptureError(f"{capture}: refused for the test")
    return held_recon(capture, out, **kw)


@pytest.fixture
def markers(tmp_path, monkeypatch):
    d = tmp_path / "markers"
    d.mkdir()
    monkeypatch.setenv("MARKERS", str(d))
    return d


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_failure_the_full_disk_cannot_record_leaves_the_worker_and_its_other_jobs_running(
        tmp_path, arun, markers, monkeypatch):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "bad")
    make_scan(root, "good")
    monkeypatch.setenv("HOLD", "1")
    tried = []

    def full(self, claim, reason, *, retry):
        tried.append(claim.job.id)
        raise OSError(errno.ENOSPC, "No space left on device", str(self.path))

    monkeypatch.setattr(Queue, "fail", full)
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, poll_s=0.05, processes=2, recon=RECON), log=lines.append)

    async def main():
        stop = asyncio.Event()
        run = asyncio.create_task(worker.run(stop))
        await _until(lambda: tried or run.done())
        await asyncio.sleep(0)  # the settle that raised has returned to the loop
        assert not run.done(), "the worker ended on the full disk"
        await _until(lambda: _starts(markers, "good"))
        (markers / "good.go").write_text("")
        await _until(lambda: worker.settled.get("good-fast") == "done" or run.done())
        stop.set()
        await run

    arun(main())
    assert tried == ["bad-fast"] and worker.settled.get("good-fast") == "done", lines
    said = [line for line in lines if line.startswith("bad-fast ended without a result")]
    assert len(said) == 1 and "[Errno 28]" in said[0] and "taken again" in said[0], lines
    assert os.path.isdir(root / "good" / "recon" / "good-fast")
