"""The demo shows what it is doing: the reconstruction's progress line (from the job's log, through the queue), the
dashboard's address while it runs and the report's path at the end."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from spadscan.worker.job_progress import parse_progress
from spadscan.demo import ReconProgress, running_job_progress


class Bar:
    """What the demo's tqdm bar is told."""

    def __init__(self, total=120.0):
        self.n, self.postfix, self.desc, self.total = 0.0, "", "", total

    def update(self, n):
        self.n += n

    def set_postfix_str(self, text):
        self.postfix = text

    def set_description_str(self, text):
        self.desc = text


def test_the_progress_line_shows_seconds_loss_and_chamfer_then_what_follows_training():
    bar = Bar()
    show = ReconProgress(bar)
    show(None)  # no job running yet
    show(parse_progress("reconstruct (fast):  20%|##   | 12/60 s [00:12<00:48, loss=3.1]"))
    assert (bar.n, bar.postfix, bar.total) == (12, "loss 3.1", 60), "the job's own training total, not the budget"
    show(parse_progress("reconstruct (fast):  50%|#####| 30/60 s [00:30<00:30, step=800, loss=2.2, chamfer=3.40mm]"))
    assert (bar.n, bar.postfix, bar.desc) == (30, "step 800, loss 2.2, checkpoint Chamfer 3.40 mm", "")
    # later in a short run: the last scored checkpoint's figure, with the step it belongs to
    show(parse_progress("reconstruct (fast):  80%|#### | 48/60 s [00:48<00:12, step=1500, loss=2.0, chamfer=3.40mm, "
                        "scored=at step 800; checkpoint 128-cell mesh; 30k points]"))
    assert bar.postfix == "step 1500, loss 2.0, checkpoint Chamfer 3.40 mm (step 800)"
    show(parse_progress("reconstruct (fast): 100%|#####| 60/60 s [01:00<00:00, loss=1.9, chamfer=2.10mm]"))
    assert bar.n == bar.total == 60 and bar.desc == ReconProgress.AFTER


def test_the_running_jobs_progress_is_found_through_the_queue(tmp_path):
    from spadscan.worker.jobs import Job
    from spadscan.worker.queue import Queue

    assert running_job_progress(tmp_path) is None  # no queue yet: nothing runs
    queue = Queue.for_root(tmp_path)
    queue.enqueue(Job(id="scan-fast", scan="scan"))
    assert running_job_progress(tmp_path) is None  # queued, not running
    claim = queue.claim()
    (queue.path / "logs").mkdir(exist_ok=True)
    (queue.path / "logs" / f"{claim.path.stem}.log").write_text("reconstruct (fast):  5%|  | 3/60 s [00:03<00:57]")
    assert running_job_progress(tmp_path).done == 3


def test_a_job_that_ended_between_two_looks_shows_its_last_progress(tmp_path):
    # A short job may start and end between two looks at the queue: its published log still has its last bar.
    from spadscan.demo import finished_job_progress

    scan = tmp_path / "scan"
    assert finished_job_progress(scan) is None, "no result yet"
    moved = scan / "recon" / "scan-fast.replaced-20260101-000000"
    moved.mkdir(parents=True)
    (moved / "report.json").write_text("{}")
    (moved / "job.log").write_text("reconstruct (fast): 100%|#| 3/3 s [00:03<00:00, step=9, loss=7.7]\n")
    assert finished_job_progress(scan) is None, "a result moved aside is not this run's"
    result = scan / "recon" / "scan-fast"
    result.mkdir()
    (result / "report.json").write_text("{}")
    (result / "job.log").write_text("loading\rreconstruct (fast):  40%|#  | 1/3 s [00:01<00:02]\r"
                                    "reconstruct (fast): 100%|###| 3/3 s [00:03<00:00, step=42, loss=2.5]\n"
                                    "spadscan reconstruct: extracting the mesh\n")
    bar = Bar()
    ReconProgress(bar)(finished_job_progress(scan))
    assert (bar.n, bar.postfix, bar.desc) == (3, "step 42, loss 2.5", ReconProgress.AFTER)


@pytest.mark.slow
def test_the_demo_prints_the_dashboard_progress_and_report(tmp_path):
    out = tmp_path / "demo"
    # The live look at the running job is switched off: a 3 s job on a busy machine may end between two looks, and
    # what the test waits for is the worker's exit, after which the demo shows the job's last bar from its log.
    code = ("import sys; import spadscan.demo as demo; demo.running_job_run = lambda captures: None; "
            "from spadscan.cli import main; sys.exit(main(sys.argv[1:]))")
    # --offline: the job after the scan, whose progress line this checks (the live demo's lines: test_live_demo.py).
    r = subprocess.run([sys.executable, "-c", code, "demo", "--out", str(out), "--views", "8", "--offline",
                        "--budget-s", "3", "--dashboard", "--dashboard-port", "0",
                        "--progress"],  # the bar (stderr is no terminal here), not plain lines
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    address = re.search(r"^dashboard: (http://127\.0\.0\.1:\d+/) ", r.stderr, re.M)
    assert address, r.stderr[-2000:]
    assert re.search(r"reconstruction \(training s\):.*\d+/3 s", r.stderr), r.stderr[-2000:]
    assert "loss " in r.stderr and "step " in r.stderr
    last = r.stdout.strip().splitlines()[-1]
    assert last.startswith("report:") and last.split()[1].endswith("report.html")
    assert (out / "summary.json").is_file() and (out / "logs" / "dashboard.log").is_file()
