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
from spadscan.worker.job_progress import claim_log
from spadscan.worker.jobs import Job, job_id_for
from spadscan.worker.queue import Queue

ODD = "demo 1+x"
"""A scan name its job's id cannot hold: the id is hashed (`<scan>-<hash>-<preset>`), not `<scan>-<preset>`."""
PROGRESS = "training: 40%|####      | 2.0/5.0 s [00:02<00:03, step=10, loss=0.5]\n"
"""A line of a job's own training bar, as its log holds it."""


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


def _fake_worker(captures: Path, bar_opened: Path) -> list[str]:
    """A `spadscan worker --once` stand-in: it runs each queued job, its bar in its log until the demo has opened a
    bar for it (`bar_opened` is there; a minute at most), publishing an empty report."""
    code = (f"import json, pathlib, time\n"
            f"from spadscan.worker.job_progress import claim_log\n"
            f"from spadscan.worker.queue import Queue\n"
            f"root, opened = pathlib.Path({str(captures)!r}), pathlib.Path({str(bar_opened)!r})\n"
            f"queue = Queue.for_root(root)\n"
            f"while (claim := queue.claim()) is not None:\n"
            f"    log = claim_log(queue.path, claim.path)\n"
            f"    log.parent.mkdir(parents=True, exist_ok=True)\n"
            f"    log.write_text({PROGRESS!r})\n"
            f"    deadline = time.monotonic() + 60\n"
            f"    while not opened.exists() and time.monotonic() < deadline:\n"
            f"        time.sleep(0.05)\n"
            f"    result = root / claim.job.scan / 'recon' / claim.job.id\n"
            f"    result.mkdir(parents=True)\n"
            f"    (result / 'report.json').write_text('{{}}')\n"
            f"    queue.finish(claim, str(result))\n"
            f"print('spadscan worker: done')\n")
    return [sys.executable, "-c", code]


class Bars:
    """The bars the demo opens: (total, description) each, and whether each was closed; `opened` (a file) is made
    when the first one opens."""

    def __init__(self, opened: Path | None = None):
        self.made, self.closed, self.opened = [], 0, opened

    def __call__(self, total, desc, unit):
        self.made.append((total, desc))
        if self.opened is not None:
            self.opened.touch()
        bars = self

        class Bar:
            def update(self, n):
                pass

            def close(self):
                bars.closed += 1

        return Bar()


@pytest.mark.parametrize("scan", ["demo-1", ODD])
def test_an_earlier_scan_is_reconstructed_first_and_said(tmp_path, a_capture, monkeypatch, scan):
    """Also for a scan whose job id does not start with its name (hashed): the job's own record names its scan."""
    captures, logs = tmp_path / "captures", tmp_path / "logs"
    _scan(captures, a_capture, scan)
    job_id = job_id_for(scan, "fast")
    Queue.for_root(captures).enqueue(Job(id=job_id, scan=scan, budget_s=5.0))
    monkeypatch.setattr(demo, "_spadscan", lambda *args: _fake_worker(captures, tmp_path / "bar-opened"))
    said, bars, procs = [], Bars(tmp_path / "bar-opened"), Processes()
    try:
        earlier = demo._reconstruct_earlier(DemoOptions(out=tmp_path, budget_s=5), captures,
                                            unreconstructed_scans(captures), procs, logs, bars, said.append)
    finally:
        procs.stop_all()
    report = captures / scan / "recon" / job_id / "report.html"
    assert said == [f"scan {scan} left complete but not reconstructed: reconstructing it first, on a bar of its own "
                    f"and outside this run's times (Ctrl-C leaves it for `spadscan worker --root {captures} "
                    f"--once`)",
                    f"earlier scan {scan} reconstructed: {report}"]
    assert earlier == [{"scan": scan, "state": "done", "report": str(report), "error": None}]
    assert bars.made == [(5.0, f"earlier scan {scan} (training s)")], "a bar of its own, named after its scan"
    assert bars.closed == 1, "the bar it opened is closed"
    assert unreconstructed_scans(captures) == [], "nothing is left for this run's worker"


def test_an_earlier_job_is_shown_on_a_bar_named_after_its_own_scan(tmp_path, a_capture):
    captures = tmp_path / "captures"
    _scan(captures, a_capture, ODD)
    queue = Queue.for_root(captures)
    queue.enqueue(Job(id=job_id_for(ODD, "fast"), scan=ODD, budget_s=5.0))
    claim = queue.claim()
    claim_log(queue.path, claim.path).parent.mkdir(parents=True, exist_ok=True)
    claim_log(queue.path, claim.path).write_text(PROGRESS)
    bars = Bars()
    show = demo.EarlierBars(captures, bars, 5.0)
    show()
    assert bars.made == [(5.0, f"earlier scan {ODD} (training s)")]
    show.close()
    assert bars.closed == 1


def test_the_earlier_scans_time_limit_allows_for_each_jobs_own_budget(tmp_path, a_capture, monkeypatch):
    """An earlier run queued its job with its own budget (`demo --budget-s 1800`, then Ctrl-C): this run's smaller
    one would cut that job off and fail the demo. A scan not queued yet is queued with this run's budget."""
    captures = tmp_path / "captures"
    _scan(captures, a_capture, "demo-1")
    Queue.for_root(captures).enqueue(Job(id=job_id_for("demo-1", "fast"), scan="demo-1", budget_s=1800.0))
    _scan(captures, a_capture, ODD)
    Queue.for_root(captures).enqueue(Job(id=job_id_for(ODD, "fast"), scan=ODD, budget_s=900.0))
    _scan(captures, a_capture, "demo-2")  # no job yet
    limits = []
    monkeypatch.setattr(demo, "_run_worker_once", lambda *args, limit_s: limits.append(limit_s) or 0)
    opts = DemoOptions(out=tmp_path, budget_s=5, stage_timeout_s=10)
    demo._reconstruct_earlier(opts, captures, ["demo-1", ODD, "demo-2"], Processes(), tmp_path / "logs", Bars(),
                              lambda line: None)
    assert limits == [(10 + 1800) + (10 + 900) + (10 + 5)]


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
