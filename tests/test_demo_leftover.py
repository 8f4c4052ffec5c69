"""A demo run stopped during its reconstruction leaves its scan complete and its job in the queue. The next run into
the same folder reconstructs that scan first, says so and shows it on a bar of its own, so that its own worker runs
only its own scan's job: the reconstruction, its time and its summary are this run's scan's alone. (The whole demo
with such a leftover: tests/e2e/test_demo.py.)"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import spadscan.demo as demo
from spadscan.demo import DemoOptions, Processes, unreconstructed_scans
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue


@pytest.fixture(scope="module")
def a_capture(tmp_path_factory) -> Path:
    """A complete 4-view capture of the demo's scene (a second's work)."""
    folder = tmp_path_factory.mktemp("sim") / "scan"
    subprocess.run([sys.executable, "-m", "spadscan.cli", "simulate", "builtin:demo", "--out", str(folder),
                    "--views", "4", "--no-progress"], check=True, capture_output=True, timeout=120)
    return folder


def _scan(captures: Path, capture: Path, name: str, state: str = "complete") -> Path:
    folder = captures / name
    shutil.copytree(capture, folder)
    manifest = json.loads((folder / "scan.json").read_text())
    manifest.update(scan_id=name, state=state, reason="stopped" if state == "aborted" else manifest.get("reason"))
    (folder / "scan.json").write_text(json.dumps(manifest))
    return folder


def _result(scan: Path, job_id: str) -> Path:
    folder = scan / "recon" / job_id
    folder.mkdir(parents=True)
    (folder / "report.json").write_text("{}")
    return folder


def test_the_scans_left_unreconstructed_are_the_complete_ones_with_no_result(tmp_path, a_capture):
    captures = tmp_path / "captures"
    queue = Queue.for_root(captures)
    _scan(captures, a_capture, "demo-3")  # reconstructed
    queue.enqueue(Job(id="demo-3-fast", scan="demo-3"))
    queue.finish(queue.claim(), str(_result(captures / "demo-3", "demo-3-fast")))
    _scan(captures, a_capture, "demo-1")  # its run was stopped during the reconstruction: the job went back
    queue.enqueue(Job(id="demo-1-fast", scan="demo-1", budget_s=5.0))
    _scan(captures, a_capture, "demo-2")  # stopped between its scan's end and the worker's first look: no job
    _scan(captures, a_capture, "demo-7")  # its worker was killed during the reconstruction: the job still running
    queue.enqueue(Job(id="demo-7-fast", scan="demo-7"))
    assert queue.claim().job.id == "demo-1-fast"
    _scan(captures, a_capture, "demo-4", "aborted")  # the worker skips it
    _scan(captures, a_capture, "demo-5", "running")  # still being recorded
    _result(_scan(captures, a_capture, "demo-6"), "demo-6-fast")  # its result is there, the queue lost: kept
    assert unreconstructed_scans(captures) == ["demo-1", "demo-2", "demo-7"]


def _fake_worker(captures: Path) -> list[str]:
    """A `spadscan worker --once` stand-in: it runs each queued job, publishing an empty report."""
    code = (f"import json, pathlib\n"
            f"from spadscan.worker.queue import Queue\n"
            f"root = pathlib.Path({str(captures)!r})\n"
            f"queue = Queue.for_root(root)\n"
            f"while (claim := queue.claim()) is not None:\n"
            f"    result = root / claim.job.scan / 'recon' / claim.job.id\n"
            f"    result.mkdir(parents=True)\n"
            f"    (result / 'report.json').write_text('{{}}')\n"
            f"    queue.finish(claim, str(result))\n"
            f"print('spadscan worker: done')\n")
    return [sys.executable, "-c", code]


class Bars:
    """The bars the demo opens: (total, description) each, and whether each was closed."""

    def __init__(self):
        self.made, self.closed = [], 0

    def __call__(self, total, desc, unit):
        self.made.append((total, desc))
        bars = self

        class Bar:
            def update(self, n):
                pass

            def close(self):
                bars.closed += 1

        return Bar()


def test_an_earlier_scan_is_reconstructed_first_and_said(tmp_path, a_capture, monkeypatch):
    captures, logs = tmp_path / "captures", tmp_path / "logs"
    _scan(captures, a_capture, "demo-1")
    Queue.for_root(captures).enqueue(Job(id="demo-1-fast", scan="demo-1", budget_s=5.0))
    monkeypatch.setattr(demo, "_spadscan", lambda *args: _fake_worker(captures))
    said, bars, procs = [], Bars(), Processes()
    try:
        earlier = demo._reconstruct_earlier(DemoOptions(out=tmp_path, budget_s=5), captures,
                                            unreconstructed_scans(captures), procs, logs, bars, said.append)
    finally:
        procs.stop_all()
    report = captures / "demo-1" / "recon" / "demo-1-fast" / "report.html"
    assert said == [f"scan demo-1 {demo.EARLIER_RUN_UNRECONSTRUCTED}: reconstructing it first, on a bar of its own "
                    f"and outside this run's times (Ctrl-C keeps it queued for `spadscan worker --root {captures} "
                    f"--once`)",
                    f"earlier scan demo-1 reconstructed: {report}"]
    assert earlier == [{"scan": "demo-1", "state": "done", "report": str(report), "error": None}]
    assert bars.closed == len(bars.made), "every bar it opened is closed"
    assert all(desc.startswith("earlier scan demo-1") for _, desc in bars.made)
    assert unreconstructed_scans(captures) == [], "nothing is left for this run's worker"


def test_an_earlier_scan_that_fails_is_said_and_the_demo_goes_on(tmp_path, a_capture, monkeypatch):
    captures, logs = tmp_path / "captures", tmp_path / "logs"
    _scan(captures, a_capture, "demo-1")
    queue = Queue.for_root(captures)
    queue.enqueue(Job(id="demo-1-fast", scan="demo-1", budget_s=5.0))
    code = (f"from spadscan.worker.queue import Queue\n"
            f"queue = Queue.for_root({str(captures)!r})\n"
            f"queue.fail(queue.claim(), 'capture demo-1: no measurements', retry=False)\n"
            f"raise SystemExit(1)\n")
    monkeypatch.setattr(demo, "_spadscan", lambda *args: [sys.executable, "-c", code])
    said, procs = [], Processes()
    try:
        earlier = demo._reconstruct_earlier(DemoOptions(out=tmp_path, budget_s=5), captures, ["demo-1"], procs,
                                            logs, Bars(), said.append)
    finally:
        procs.stop_all()
    assert said[-1] == (f"earlier scan demo-1 not reconstructed (failed: capture demo-1: no measurements); "
                        f"`spadscan worker --root {captures} --status` says more")
    assert earlier[0]["state"] == "failed"
