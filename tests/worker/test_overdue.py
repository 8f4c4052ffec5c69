"""A job process that runs far past its time budget (hung, stopped, waiting on a file that never answers) is stopped
by its worker and recorded as a crash that says why, so the queue behind it moves on; within its limit, or without a
budget, a job runs on."""

from __future__ import annotations

import json
import re
import signal
from pathlib import Path

import pytest

from spadscan.worker import overdue
from spadscan.worker.overdue import overdue_limit_s, overdue_reason
from spadscan.worker.pool import Worker
from spadscan.worker.watcher import JobOptions
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan

pytestmark = pytest.mark.usefixtures("recon_stand_ins")  # the job processes import hung_recon


def hung_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
               started=None):
    """A stand-in reconstruction whose process hangs and ignores SIGTERM (a process stopped or stuck in the kernel
    takes no signal but SIGKILL): the worker's SIGKILL after its grace period ends it."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    while True:
        signal.pause()


def test_the_limit_is_twice_the_budget_and_five_minutes():
    assert overdue_limit_s(60.0) == 420.0
    assert overdue_reason(None, 1e9) is None, "no budget: no limit"
    assert overdue_reason((60.0, 1000.0), 1000.0 + 420.0) is None
    why = overdue_reason((60.0, 1000.0), 1000.0 + 421.0)
    assert why.startswith("stopped by the worker 06:01 past its 01:00 budget") and "\n" not in why
    assert "2 times its budget and 05:00 more" in why
    assert overdue_reason((60.0, float("nan")), 2000.0) is None


def test_a_hung_job_is_stopped_and_its_crash_says_why(tmp_path, arun, monkeypatch):
    monkeypatch.setattr(overdue, "OVERDUE_FACTOR", 1.0)
    monkeypatch.setattr(overdue, "OVERDUE_GRACE_S", 0.5)
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    lines: list[str] = []
    config = WorkerConfig(root=root, once=True, poll_s=0.1, stop_grace_s=1, max_attempts=2,
                          recon="test_overdue:hung_recon", options=JobOptions(budget_s=0.5))
    assert arun(Worker(config, log=lines.append).run(), timeout_s=120) == {"s-fast": "failed"}, lines
    stopped = [line for line in lines if "past its 00:00 budget" in line]
    assert len(stopped) == 4, lines  # each attempt: the stop said, then its crash
    assert re.match(r"stopped by the worker \d\d:\d\d past its 00:00 budget", Worker(config).queue.last_error("s-fast"))


def test_a_job_within_its_limit_is_not_stopped(tmp_path, arun, monkeypatch):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    lines: list[str] = []
    config = WorkerConfig(root=root, once=True, poll_s=0.1, recon="test_overdue:quick_recon",
                          options=JobOptions(budget_s=0.5))
    assert arun(Worker(config, log=lines.append).run(), timeout_s=120) == {"s-fast": "done"}, lines
    assert not any("stopped by the worker" in line for line in lines)


def quick_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                started=None):
    """A stand-in reconstruction that takes a little past its 0.5 s budget, as a slow end of a run does."""
    import time

    time.sleep(1.0)
    report = {"steps": 1}
    (Path(out) / "report.json").write_text(json.dumps(report))
    return report
