"""A demo whose reconstruction job fails ends in one error line, also when the worker retried the job first.

The worker runs a crashed job again; the next attempt's training bar may have a shorter total than the last one
(its set-up took longer). The demo's bar starts over for it, named after the attempt; a reading no claim tells
apart never takes the bar's total below its count: tqdm reads a count past the total as "no total", which the
demo's `{total:.0f}` cannot format (the bar then raised on every redraw, and at its close, in place of the demo's
error line).
"""

from __future__ import annotations

import io

import pytest
from tqdm import tqdm

import spadscan.demo as demo
from spadscan.cli import main
from spadscan.worker.job_progress import parse_progress

ATTEMPTS = [  # what the worker's job log shows, look after look: a first attempt's full bar, then the retry's
    ("c1", 1, "reconstruct (fast):  50%|#####     | 4/8 s [00:04<00:04, step=100, loss=0.7]"),
    ("c1", 1, "reconstruct (fast): 100%|##########| 8/8 s [00:08<00:00, step=216, loss=0.6]"),
    ("c2", 2, "reconstruct (fast):   0%|          | 0/7 s [00:00<?]"),
    ("c2", 2, "reconstruct (fast):  43%|####      | 3/7 s [00:03<00:04, step=14, loss=5.19]"),
    ("c2", 2, "reconstruct (fast): 100%|##########| 7/7 s [00:07<00:00, step=200, loss=0.61]"),
]


def run_of(claim, attempt, line):
    return demo.JobRun("scan-fast", claim, attempt, parse_progress(line), "job process died" if attempt > 1 else None)

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
    monkeypatch.setattr(demo, "running_job_run", lambda captures: run_of(*next(looks)))

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


def test_the_retry_starts_the_bar_over_within_its_total():
    bar = tqdm(total=20, file=io.StringIO(), bar_format="{n:.0f}/{total:.0f}")
    show = demo.ReconProgress(bar)
    for look in ATTEMPTS:
        show.follow(run_of(*look))
        assert bar.n <= bar.total, look
    assert (bar.n, bar.total) == (7, 7), "the retry's own bar"
    bar.close()


def test_readings_no_claim_tells_apart_never_count_past_the_total():
    bar = tqdm(total=20, file=io.StringIO(), bar_format="{n:.0f}/{total:.0f}")
    show = demo.ReconProgress(bar)
    for _, _, line in ATTEMPTS:
        show(parse_progress(line))
        assert bar.n <= bar.total, line
    assert bar.total == 8, "taken for one run: the total it counted stays"
    bar.close()


def test_the_demos_bar_follows_the_retry_from_its_start(tmp_path, capsys, no_devices):
    out = tmp_path / "demo"
    main(["demo", "--out", str(out), "--offline", "--views", "4", "--budget-s", "20", "--scene", "sphere",
          "--progress"])  # the bar (stderr is no terminal here), not plain lines
    err = capsys.readouterr().err
    assert "reconstruction job scan-fast: the worker runs it again, attempt 2 (the last attempt: job process died)" \
        in err
    assert "reconstruction (training s), attempt 2:  43%" in err and "3/7 s" in err, err
