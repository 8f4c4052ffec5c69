"""The full disk a job met is the one named and waited on: the queue's own disk (`--queue` on another disk than the
captures root) when the job's log or outcome file did not fit there, the captures' disk when its result did not. And
a job that finished, whose small outcome file alone met the full disk, is published, not reconstructed again."""

from __future__ import annotations

import asyncio
import errno
import json
import os
import sys
from pathlib import Path

import pytest

import spadscan.worker.disk_room as disk_room
from spadscan.worker.disk_room import full_folder
from spadscan.worker.jobs import COMPLETE, Job
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan
from test_worker_disk_full import JOB, fill_leaving, run_worker, small_disk, until


def runs(marker: Path) -> int:
    """How many times a stand-in below ran (one line each in `marker`)."""
    return len(marker.read_text().splitlines()) if marker.exists() else 0


def _ran() -> int:
    marker = Path(os.environ["RUNS"])
    with open(marker, "a") as f:
        f.write("ran\n")
    return runs(marker)


def queue_filling_recon(capture, out, **kwargs):
    """A stand-in reconstruction whose first run fills the queue's disk (the folder $QUEUE_DISK) and then writes to
    its log (stderr, a file in the queue's logs/): ENOSPC with no file name, as any library's progress line meets
    it. Later runs write a result."""
    if _ran() == 1:
        fill_leaving(Path(os.environ["QUEUE_DISK"]), 0)
        for _ in range(1000):
            print("step " + "." * 100, file=sys.stderr, flush=True)
    (Path(out) / "report.json").write_text("{}")
    return {}


def finished_unsaid_recon(capture, out, **kwargs):
    """A stand-in reconstruction that finishes (a mesh, a report with a Chamfer) while the queue's disk has just
    filled up: the job process's outcome file meets ENOSPC."""
    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    _ran()
    (Path(out) / "mesh.ply").write_text("ply\n")
    report = {"chamfer_mm": 1.5, "warnings": ["a warning of its own"]}
    (Path(out) / "report.json").write_text(json.dumps(report))
    # this runs in the job's own process (`python -m spadscan.worker.jobs`: its __main__): only its outcome is refused
    for name in ("__main__", "spadscan.worker.jobs"):
        if hasattr(sys.modules.get(name), "_write_outcome"):
            sys.modules[name]._write_outcome = full
    return report


def test_a_full_disk_error_without_a_file_name_is_blamed_on_the_fullest_disk(tmp_path, monkeypatch):
    result, queue_tmp = tmp_path / "caps" / "s" / "recon" / ".tmp-s-fast-x", tmp_path / "queue" / "tmp"
    free = {result: 10**12, queue_tmp: 0}
    devices = {result: 1, queue_tmp: 2}
    monkeypatch.setattr(disk_room, "_device", lambda folder: devices[Path(folder)])
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: free[Path(folder)])
    nameless = OSError(errno.ENOSPC, "No space left on device")
    assert full_folder(nameless, [result, queue_tmp]) == queue_tmp, "the queue's disk, on a disk of its own, is full"
    free.update({result: 0, queue_tmp: 10**12})
    assert full_folder(nameless, [result, queue_tmp]) == result
    devices[queue_tmp] = 1
    free.update({result: 5, queue_tmp: 0})
    assert full_folder(nameless, [result, queue_tmp]) == result, "one disk: the job's result folder is named"
    named = OSError(errno.ENOSPC, "No space left on device", str(queue_tmp / "outcome.json"))
    assert full_folder(named, [result, queue_tmp]) == queue_tmp, "the file an error names says where"


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_full_queue_disk_is_the_one_named_and_waited_on(tmp_path, monkeypatch, arun):
    """The queue on a small disk of its own fills while the job runs: the job's log line meets ENOSPC, with no file
    name, and its outcome file does not fit either. The worker names the queue's folder and its disk, waits for room
    there (not on the captures' disk, which has plenty and would end the wait at once), and runs the job once room
    is made."""
    with small_disk(tmp_path / "qdisk", "4m") as qdisk:
        root = tmp_path / "caps"
        make_scan(root, "s")
        queue_dir = qdisk / "q"
        Queue(queue_dir).enqueue(Job(id=JOB, scan="s"))
        monkeypatch.setenv("QUEUE_DISK", str(qdisk))
        monkeypatch.setenv("RUNS", str(tmp_path / "runs"))
        lines: list[str] = []
        worker = Worker(WorkerConfig(root=root, queue_dir=queue_dir, once=True, poll_s=0.05, max_attempts=1,
                                     recon="test_room_wait_queue_disk:queue_filling_recon"), log=lines.append)

        async def scenario():
            async def meanwhile():
                await until(lambda: any("waiting for room" in line for line in lines), "the wait for room")
                assert runs(tmp_path / "runs") == 1
                (qdisk / "filler").unlink()

            return (await run_worker(worker, meanwhile))[1]

        assert arun(scenario()) == {JOB: "done"}, lines
        (stopped,) = [line for line in lines if line.startswith(f"{JOB} stopped after ")]
        assert f"no room left on the disk: {queue_dir / 'tmp'} could not be written" in stopped, stopped
        assert f"make room on the filesystem mounted at {qdisk}, then this worker runs it again" in stopped, stopped
        (waiting,) = [line for line in lines if "waiting for room" in line]
        assert waiting.startswith(f"waiting for room on {qdisk} before claiming another job: "), waiting
        assert any(line.startswith(f"room again on {qdisk} (") for line in lines), lines
        full, done = worker.queue.records(JOB)
        assert (full["outcome"], done["outcome"]) == ("disk_full", "done")
        assert (full["room"]["mount"], full["room"]["folder"]) == (str(qdisk), str(queue_dir / "tmp"))


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_finished_job_whose_outcome_file_does_not_fit_is_published_not_reconstructed_again(tmp_path, monkeypatch,
                                                                                              arun):
    """Its result is whole in its scratch folder; only the outcome file (a few hundred bytes, in the queue's tmp/)
    met the full disk. The job process says so by its exit status, and the worker publishes the result, its done
    line read from the result's report."""
    monkeypatch.setenv("RUNS", str(tmp_path / "runs"))
    root = tmp_path / "caps"
    make_scan(root, "s")
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05, max_attempts=1,
                                 recon="test_room_wait_queue_disk:finished_unsaid_recon"), log=lines.append)
    assert arun(asyncio.wait_for(worker.run(), 90)) == {JOB: "done"}, lines
    assert runs(tmp_path / "runs") == 1, "reconstructed once"
    assert [r["outcome"] for r in worker.queue.records(JOB)] == ["done"]
    result = root / "s" / "recon" / JOB
    assert (result / "mesh.ply").exists() and (result / COMPLETE).exists()
    assert any(line.startswith(f"{JOB}: finished, but its outcome file did not fit in {worker.queue.path / 'tmp'} "
                               f"(no room left on the disk): publishing its result all the same") for line in lines), \
        lines
    (done,) = [line for line in lines if line.startswith(f"{JOB} done in ")]
    assert f"Chamfer 1.50 mm -> {result}\n  warning: a warning of its own" in done, done
