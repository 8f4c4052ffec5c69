"""A job beside other workers on its machine knows their job processes (SPADSCAN_MACHINE_JOBS, which the worker
puts into its environment): its busy warning names them among the processes that held the cores, and advises fewer
job processes on the host rather than stopping other work. Every figure here is injected: nothing depends on the
machine's load."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from spadscan.worker.cpu_wait import MACHINE_JOBS_ENV, machine_jobs
from spadscan.worker.end_of_run import RunFacts, busy_warning
from spadscan.worker.pool import Worker
from spadscan.worker.presence import machine_siblings
from spadscan.worker.threads import ADAPT_ENV, ENV
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan
from test_workers_share_cores import cores, sibling

HERE = Path(__file__).resolve().parent
FLAT = [1.0] * 100  # a data term that settled: the busy line is the only one to read
ONE_THREAD = {"main": [4.5, 5.5], "helpers": []}  # waited 55 % of 10 s: starved, by other processes alone
SPINNING = {"main": [9.8, 9.6], "helpers": [[9.4, 9.4]]}  # a helper that counts: the run's own threads too
SIBLINGS = "among them up to 2 job process(es) of other workers on this host"
FEWER = "run fewer job processes on this host (fewer workers, or a smaller --processes)"


@pytest.fixture
def no_user_env(monkeypatch):
    for name in (ENV, ADAPT_ENV, MACHINE_JOBS_ENV):
        monkeypatch.delenv(name, raising=False)


def facts(times: dict | None = ONE_THREAD, cpu_s: float = 4.5, **kw) -> RunFacts:
    return RunFacts("budget", 150, True, FLAT, cpu_seconds=cpu_s, wall_seconds=10.0, thread_times=times, **kw)


# ---- the worker names them to the job ------------------------------------------------------------------------

def test_the_job_environment_names_the_other_workers_job_processes():
    config = WorkerConfig(root=Path("."), processes=1)
    assert config.job_env({}, others=3)[MACHINE_JOBS_ENV] == "3"
    assert MACHINE_JOBS_ENV not in config.job_env({}), "alone: nothing to name"
    assert config.job_env({MACHINE_JOBS_ENV: "5"})[MACHINE_JOBS_ENV] == "0", "the worker's own is not the job's"
    fixed = WorkerConfig(root=Path("."), processes=1, threads=2)
    assert fixed.job_env({}, others=2)[MACHINE_JOBS_ENV] == "2", "kept threads or not, they share the host"
    chosen = WorkerConfig(root=Path("."), processes=1, child_env={MACHINE_JOBS_ENV: "7"})
    assert chosen.job_env({}, others=2)[MACHINE_JOBS_ENV] == "7", "child_env has the last word, as for the threads"


def test_a_worker_names_the_siblings_it_shares_the_cores_with(tmp_path, monkeypatch, arun, no_user_env):
    cores(monkeypatch, 2)
    root = tmp_path / "captures"
    root.mkdir()
    worker = Worker(WorkerConfig(root=root, poll_s=0.05), log=lambda line: None)
    worker._share_cores(machine_siblings(worker.queue.path, worker.presence.holder))
    assert MACHINE_JOBS_ENV not in worker.job_env
    sibling(worker.queue.path, processes=2)
    arun(worker._share_cores_now())
    assert worker.job_env[MACHINE_JOBS_ENV] == "2" and worker.job_env[ENV] == "1"


def env_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
              started=None):
    """A stand-in reconstruction that reports what its process was told of the other workers' jobs."""
    report = {"machine_jobs": os.environ.get(MACHINE_JOBS_ENV)}
    (Path(out) / "report.json").write_text(json.dumps(report))
    return report


def test_a_job_process_beside_another_worker_is_told_its_job_processes(tmp_path, monkeypatch, arun, no_user_env):
    cores(monkeypatch, 2)
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")]))
    sibling(root / ".queue", processes=3)
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05, recon="test_busy_sibling_workers:env_recon"),
                    log=lines.append)
    assert arun(worker.run(), timeout_s=120) == {"s-fast": "done"}, lines
    report = json.loads((root / "s" / "recon" / "s-fast" / "report.json").read_text())
    assert report["machine_jobs"] == "3"


# ---- the job reads it ----------------------------------------------------------------------------------------

def test_the_count_is_read_and_a_bad_one_is_ignored_in_one_line():
    assert machine_jobs({}) == (None, None)
    assert machine_jobs({MACHINE_JOBS_ENV: "0"}) == (0, None)
    assert machine_jobs({MACHINE_JOBS_ENV: " 12\n"}) == (12, None)
    for bad in ("", "x", "-1", "1.5", "+2", "1_0", "\u0663", "99999999", "1" * 5000):
        count, warning = machine_jobs({MACHINE_JOBS_ENV: bad})
        assert count is None and warning.startswith(f"{MACHINE_JOBS_ENV}=") and "ignored" in warning, bad
        assert "\n" not in warning, bad


# ---- the busy line -------------------------------------------------------------------------------------------

def test_beside_other_workers_jobs_the_busy_line_names_them_and_advises_fewer_job_processes():
    line = busy_warning(facts(machine_jobs=2))
    assert line == ("the machine was busy: this run's threads waited for CPU cores for 55 % of its training (other "
                    f"processes held them, {SIBLINGS}, whose share of the cores this run's threads already count); "
                    f"it trained about 2x slower than it would alone (150 steps); {FEWER} or give it a larger time "
                    "budget"), line
    assert "stop other work" not in line


def test_without_other_workers_jobs_the_busy_line_is_as_before():
    before = busy_warning(facts())
    assert before.endswith("(other processes held them); it trained about 2x slower than it would alone (150 steps); "
                           "stop other work or give it a larger time budget"), before
    assert busy_warning(facts(machine_jobs=0)) == before, "a worker alone on its host"


def test_the_runs_own_threads_and_a_spin_are_still_said_beside_other_workers():
    line = busy_warning(facts(SPINNING, cpu_s=9.6, machine_jobs=2))
    assert (f"(other processes held them, {SIBLINGS}, whose share of the cores this run's threads already count, or "
            "the run has more threads than cores free to it) (its CPU time, 0.96 of a core, hides this") in line, line
    assert line.endswith(f"; {FEWER}, run it with `--threads 1`, or give it a larger time budget"), line


def test_threads_the_run_kept_did_not_count_the_other_workers_jobs():
    line = busy_warning(facts(machine_jobs=2, threads_fixed=True))
    assert f"(other processes held them, {SIBLINGS}, beside which this run kept the threads it was given)" in line
    assert "already count" not in line and FEWER in line, line


def test_judged_by_its_cpu_time_the_line_names_them_too():
    line = busy_warning(facts(None, cpu_s=2.0, machine_jobs=2))
    assert line == ("the machine was busy: this run had 0.20 of a CPU core on average (beside up to 2 job process(es) "
                    "of other workers on this host, whose share of the cores this run's threads already count) and "
                    f"trained about 5x slower than it would alone (150 steps); {FEWER} or give it a larger time "
                    "budget"), line
    assert busy_warning(facts(None, cpu_s=2.0)).endswith("; stop other work or give it a larger time budget")


def test_a_run_that_was_not_starved_says_nothing_beside_other_workers_either():
    assert busy_warning(facts({"main": [8.0, 2.0], "helpers": []}, cpu_s=8.0, machine_jobs=3)) is None
