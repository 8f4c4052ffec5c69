"""A demo whose reconstruction job fails ends in one error line, also when the worker retried the job first.

The worker runs a crashed job again; the next attempt's training bar may have a shorter total than the last one
(its set-up took longer), so the demo's bar is told a total below the count it already shows. tqdm reads a count
past the total as "no total", which the demo's `{total:.0f}` cannot format: the bar then raised on every redraw,
and at its close, in place of the demo's error line.
"""

from __future__ import annotations

import io

import pytest
from tqdm import tqdm

import spadscan.demo as demo
from spadscan.cli import main
from spadscan.worker.job_progress import parse_progress

ATTEMPTS = [  # what the worker's job log shows, look after look: a first attempt's full bar, then the retry's
    "reconstruct (fast):  50%|#####     | 4/8 s [00:04<00:04, step=100, loss=0.7]",
    "reconstruct (fast): 100%|##########| 8/8 s [00:08<00:00, step=216, loss=0.6]",
    "reconstruct (fast):   0%|          | 0/7 s [00:00<?]",
    "reconstruct (fast):  43%|####      | 3/7 s [00:03<00:04, step=14, loss=5.19]",
    "reconstruct (fast): 100%|##########| 7/7 s [00:07<00:00, step=200, loss=0.61]",
]
WORKER_SAYS = "spadscan worker: 0 done, 1 failed (scan-fast)"


@pytest.fixture
def no_devices(monkeypatch):
    """The demo's run without its processes: no daemon, no scan; the reconstruction stage is the real one, with a
    worker whose job crashed twice (the look at the running job reads ATTEMPTS, one after the other)."""
    monkeypatch.setattr(demo.Processes, "start", lambda self, name, argv, log: None)
    monkeypatch.setattr(demo, "_wait_for_daemon", lambda *args, **kwargs: None)
    monkeypatch.setattr(demo, "_abort_earlier_scans", lambda *args: [])
    monkeypatch.setattr(demo, "_scan", lambda sock, name, opts, progress, watch=None: progress.update(opts.views))
    monkeypatch.setattr(demo, "call", lambda *args, **kwargs: None)
    looks = iter(ATTEMPTS)
    monkeypatch.setattr(demo, "running_job_progress", lambda captures: parse_progress(next(looks)))

    def worker_once(opts, captures, procs, logs, tick, limit_s):
        for _ in ATTEMPTS:
            tick()
        (logs / "worker.log").write_text(WORKER_SAYS + "\n")
        return 1

    monkeypatch.setattr(demo, "_run_worker_once", worker_once)


def test_a_failed_job_ends_the_demo_in_one_error_line(tmp_path, capsys, no_devices):
    out = tmp_path / "demo"
    code = main(["demo", "--out", str(out), "--offline", "--views", "4", "--budget-s", "20", "--scene", "sphere"])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert code == 1
    last = err.strip().splitlines()[-1]
    assert last == f"spadscan: error: the worker exited with code 1: {WORKER_SAYS} (log: {out / 'logs' / 'worker.log'})"


def test_the_bar_never_counts_past_its_total():
    bar = tqdm(total=20, file=io.StringIO(), bar_format="{n:.0f}/{total:.0f}")
    show = demo.ReconProgress(bar)
    for line in ATTEMPTS:
        show(parse_progress(line))
        assert bar.n <= bar.total, line
    assert bar.total == 8, "the first attempt's total stays: the bar has counted it"
    bar.close()
