"""A job process whose worker is already gone when it starts exits at once, by its start-up check alone (the watch
thread's poll is made too slow to catch it in the test's time)."""

from __future__ import annotations

import os
import subprocess
import sys

from spadscan.worker.jobs import EXIT_CRASH

SCRIPT = ("import sys, time\n"
          "from spadscan.worker.jobs import _exit_with_parent\n"
          "_exit_with_parent(int(sys.argv[1]), poll_s=3600.0)\n"
          "print('running', flush=True)\n")


def run_job_like(parent: int) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SCRIPT, str(parent)], capture_output=True, text=True, timeout=120)


def test_a_job_started_by_a_worker_that_is_gone_exits_at_start_up():
    gone = run_job_like(parent=os.getpid() + 1_000_000)  # no such parent: the worker died before the job started
    assert gone.returncode == EXIT_CRASH and "running" not in gone.stdout, gone


def test_a_job_whose_worker_is_its_parent_runs():
    alive = run_job_like(parent=os.getpid())
    assert alive.returncode == 0 and "running" in alive.stdout, alive
