"""A full disk while a finished job's result is published: the worker says so once, keeps the result and its other
jobs, and publishes it when there is room again; a worker stopped meanwhile leaves the result for the next one."""

from __future__ import annotations

import asyncio
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import spadscan.worker.publishing as publishing
from spadscan.worker.jobs import COMPLETE
from spadscan.worker.pool import Worker
from spadscan.worker.worker_config import WorkerConfig

from process_helpers import reaped
from test_watcher import make_scan
from test_worker_trouble import _until

HERE = Path(__file__).resolve().parent
RECON = "test_worker_publish_full:held_recon"
COPYFILE = shutil.copyfile


def held_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
               started=None):
    """A stand-in reconstruction that starts (`<scan>.<pid>.start` in $MARKERS), waits until the test writes
    `<scan>.go` there (at once without $HOLD), and writes a mesh and a report."""
    markers = Path(os.environ["MARKERS"])
    name = Path(capture).name
    (markers / f"{name}.{os.getpid()}.start").write_text("")
    while os.environ.get("HOLD") and not (markers / f"{name}.go").exists():
        time.sleep(0.02)
    (Path(out) / "mesh.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\nend_header\n")
    report = {"preset": preset, "capture": str(capture)}
    (Path(out) / "report.json").write_text(json.dumps(report))
    return report


class FullDisk:
    """shutil.copyfile as publishing calls it (the job's log copied into its result), failing with ENOSPC while
    `full` is set, as it does when another program has filled the disk."""

    def __init__(self):
        self.full = True
        self.failures = 0

    def __call__(self, src, dst, *args, **kwargs):
        if self.full:
            self.failures += 1
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        return COPYFILE(src, dst, *args, **kwargs)


@pytest.fixture
def markers(tmp_path, monkeypatch):
    d = tmp_path / "markers"
    d.mkdir()
    monkeypatch.setenv("MARKERS", str(d))
    return d


def _starts(markers: Path, scan: str) -> list[Path]:
    return sorted(markers.glob(f"{scan}.*.start"))


def _scratch(root: Path, scan: str) -> list[Path]:
    return sorted((root / scan / "recon").glob(".tmp-*"))


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_full_disk_while_publishing_keeps_the_result_and_the_other_jobs_and_publishes_it_later(
        tmp_path, arun, markers, monkeypatch):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "a")
    make_scan(root, "b")
    monkeypatch.setenv("HOLD", "1")
    disk = FullDisk()
    monkeypatch.setattr(publishing.shutil, "copyfile", disk)
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, poll_s=0.05, processes=2, recon=RECON), log=lines.append)
    seen = {}

    async def main():
        stop = asyncio.Event()
        run = asyncio.create_task(worker.run(stop))
        await _until(lambda: _starts(markers, "a") and _starts(markers, "b"))
        (markers / "a.go").write_text("")  # a finishes while b still runs; the disk is full
        await _until(lambda: disk.failures >= 3 or run.done())  # publishing it was tried again at later polls
        seen["scratch"] = [sorted(p.name for p in d.iterdir()) for d in _scratch(root, "a")]
        seen["b running"] = "b-fast" in worker.children and worker.children["b-fast"].proc.returncode is None
        seen["worker running"] = not run.done()
        seen["a state"] = worker.queue.job_paths()["a-fast"][0]
        assert not run.done(), "the worker ended on the full disk"
        disk.full = False  # room again
        await _until(lambda: worker.settled.get("a-fast") == "done")
        (markers / "b.go").write_text("")
        await _until(lambda: worker.settled.get("b-fast") == "done")
        stop.set()
        await run

    arun(main())
    assert seen["scratch"] == [["job.json", "mesh.ply", "report.json"]], "the finished result was kept"
    assert seen["b running"] and seen["worker running"], "the worker and its other job went on"
    assert seen["a state"] == "running", "the job stayed held by this worker"
    result = root / "a" / "recon" / "a-fast"
    assert {"mesh.ply", "report.json", "job.log", COMPLETE} <= {p.name for p in result.iterdir()}
    assert _scratch(root, "a") == []
    assert len(_starts(markers, "a")) == 1, "the job was not run again"
    assert worker.queue.attempts("a-fast") == 1
    trouble = [line for line in lines if "publish the finished result of a-fast" in line]
    assert len(trouble) == 2, lines  # said once while it kept failing, and once when it worked again
    assert trouble[0].startswith("could not publish the finished result of a-fast (") and "[Errno 28]" in trouble[0]
    assert trouble[1].startswith("could publish the finished result of a-fast (")
    assert any(line.startswith("a-fast done in ") and line.endswith(f"-> {result}") for line in lines), lines


LAUNCH = """
import asyncio, errno, sys
import spadscan.worker.publishing as publishing
from spadscan.worker.pool import run_worker
from spadscan.worker.worker_config import WorkerConfig

def full(src, dst, *args, **kwargs):  # the disk stays full: the job's log never fits
    raise OSError(errno.ENOSPC, "No space left on device", str(dst))

publishing.shutil.copyfile = full
asyncio.run(run_worker(WorkerConfig(root=sys.argv[1], poll_s=0.05, recon=%r)))
""" % RECON


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_worker_stopped_before_it_could_publish_leaves_the_result_for_the_next_one(tmp_path, markers):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "a")
    log = tmp_path / "worker.log"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")])}
    with open(log, "w") as out, reaped(subprocess.Popen([sys.executable, "-c", LAUNCH, str(root)], env=env,
                                                         stdout=out, stderr=subprocess.STDOUT)) as (first,):
        deadline = time.monotonic() + 60
        while "could not publish the finished result of a-fast" not in log.read_text():
            assert first.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        first.send_signal(signal.SIGTERM)  # systemctl stop while the disk is still full
        assert first.wait(timeout=60) == 0, log.read_text()
    said = log.read_text()
    assert "a-fast stopped before its result could be published; back in the queue, its finished result stays in" \
        in said, said
    lines: list[str] = []
    second = Worker(WorkerConfig(root=root, poll_s=0.05, once=True, recon=RECON), log=lines.append)
    asyncio.run(second.run())
    result = root / "a" / "recon" / "a-fast"
    assert (result / "mesh.ply").is_file() and (result / COMPLETE).is_file(), lines
    assert len(_starts(markers, "a")) == 1, "published as it was, not reconstructed again"
    assert any("published the finished result" in line for line in lines), lines
    assert second.queue.job_paths()["a-fast"][0] == "done"
