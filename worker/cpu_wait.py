"""What a CPU run lost to other processes: how long its threads waited for a core (Linux's scheduler statistics).

A process's CPU seconds over its wall seconds (`end_of_run.cpu_share`) tell how much of a core it had, not what it
lost: OpenMP threads that spin at their barriers burn CPU while a partner that lost its core keeps them waiting.
Measured on a 2-core machine (the fast preset, a 64-view sphere, 200 steps, against the same run alone), two threads
that spin 30,000 times before they sleep (GOMP_SPINCOUNT=30000) beside one CPU-bound process made 9.5-16 times fewer
steps while their CPU time read 0.92-0.99 of a core: no warning, or "about 1x fewer".

Linux keeps for each thread (/proc/self/task/TID/schedstat) its nanoseconds on a CPU and its nanoseconds runnable but
waiting on a run queue while other threads held the cores. What a run lost is read from its threads' waits:
- the stepping thread's (the one that calls the model's step: torch issues every operation from it), all of it;
- each other thread's (OpenMP's workers) that was runnable, on a CPU or waiting for one, at least RUNNABLE_SHARE of
  the time, all of it: such a thread spins at the barriers (or works beside the stepping thread), and while it waits
  for a core its partners spin or sleep at the next barrier (the spinning pair above: runnable 76-94 % of the time;
  their waits summed give 9.6-20x fewer steps against 9.5-16x measured, beside two processes 6.6-11x against
  4.7-8.1x: the waits of two threads overlap there, and their sum errs high);
- nothing of a thread asleep most of the time: a passive worker is woken for each parallel operation (runnable 30-38
  % of the time), and its waits fall while the stepping thread does its own part (two passive threads beside two
  processes: the stepping thread's wait alone gives 1.8-1.9x against 1.7-1.8x measured; with the worker's waits
  added, 2.7-3.3x).

`end_of_run` turns it into the busy-machine warning (docs/end_of_run.md gives the measurements). Where the statistics
cannot be read (not Linux, a kernel without them), nothing is measured and the warning falls back on the CPU time.
"""

from __future__ import annotations

import math
import os
import threading
from pathlib import Path
from typing import Callable

from .env_number import whole_number

TASKS = Path("/proc/self/task")
"""One folder per thread of this process, each holding `schedstat`: ns on a CPU, ns waiting on a run queue, slices."""

RUNNABLE_SHARE = 0.5
"""Share of the time a helper thread must have been runnable for its waits to count as the run's (the module's rule:
the measured spinning workers were runnable 76-94 % of it, passive ones 30-38 %)."""

MAIN_SEEN_SHARE = 0.5
"""Share of training's wall time the stepping thread's figures (on a CPU plus waiting) must cover to be believed: a
kernel that keeps no scheduler statistics reads zeros, which would pass for a run that lost nothing (measured: the
stepping thread's figures cover 0.97-0.99 of training)."""

MACHINE_JOBS_ENV = "SPADSCAN_MACHINE_JOBS"
"""Set by the worker for each job process it starts beside other workers on its machine: how many job processes
those may run at once (`worker_config.machine_job_processes`), among which the job's share of the cores was counted.
Cores its threads waited for may have been held by them, and the busy machine's advice then is fewer job processes
on the host, not to stop other work (`end_of_run.busy_warning`)."""
MAX_MACHINE_JOBS = 1_000_000
"""The most job processes MACHINE_JOBS_ENV may name: a larger figure is no count the worker writes."""

Times = dict[int, tuple[float, float]]
"""{thread id: (seconds on a CPU, seconds waiting on a run queue)}, since each thread began."""


def read_threads(tasks: Path = TASKS) -> Times | None:
    """Each live thread's seconds on a CPU and waiting for one, or None where the statistics cannot be read. A thread
    that ends while it is read is left out."""
    try:
        names = os.listdir(tasks)
    except OSError:
        return None
    times: Times = {}
    for name in names:
        try:
            with open(tasks / name / "schedstat", "rb") as f:
                fields = f.read().split()
            times[int(name)] = (int(fields[0]) * 1e-9, int(fields[1]) * 1e-9)
        except FileNotFoundError:  # the thread ended between the listing and the read
            continue
        except (OSError, ValueError, IndexError):
            return None
    return times or None


class ThreadWaits:
    """Each thread's seconds on a CPU and waiting for one, summed over the stretches between `resume()` and
    `pause()` (training's steps, its checkpoint evaluations left out). `reader` gives the threads' times since they
    began (`read_threads`; tests inject their own). `main`: the stepping thread's id (default: the thread that
    calls `resume`). Once a reading fails the whole is unknown (`summary` None): a partial sum reads as an idle
    machine."""

    def __init__(self, reader: Callable[[], Times | None] = read_threads, main: int | None = None):
        self.reader, self.main = reader, main
        self.run: dict[int, float] = {}
        self.wait: dict[int, float] = {}
        self.known = True
        self._before: Times | None = None

    def resume(self) -> None:
        """A stretch begins."""
        if self.main is None:
            self.main = threading.get_native_id()
        self._before = self._read()

    def pause(self) -> None:
        """The stretch that `resume` began ends: its threads' times are added."""
        before, self._before = self._before, None
        after = self._read() if before is not None else None
        if before is None or after is None:
            return
        for tid, (run, wait) in after.items():
            run0, wait0 = before.get(tid, (0.0, 0.0))  # a thread born in the stretch: all its time lies in it
            self.run[tid] = self.run.get(tid, 0.0) + max(0.0, run - run0)
            self.wait[tid] = self.wait.get(tid, 0.0) + max(0.0, wait - wait0)

    def _read(self) -> Times | None:
        if not self.known:
            return None
        times = self.reader()
        if times is None:
            self.known = False
        return times

    def summary(self) -> dict | None:
        """{"main": [run_s, wait_s] of the stepping thread, "helpers": [[run_s, wait_s], ...] of the others that
        ran or waited}, plain data for `lost_seconds`; None where the times are unknown or no stretch ended."""
        if not self.known or self.main not in self.run:
            return None
        helpers = [[self.run[t], self.wait[t]] for t in sorted(self.run) if t != self.main
                   and self.run[t] + self.wait[t] > 0]
        return {"main": [self.run[self.main], self.wait[self.main]], "helpers": helpers}


def machine_jobs(environ) -> tuple[int | None, str | None]:
    """(the job processes of other workers on this machine that `environ`'s MACHINE_JOBS_ENV names, or None where it
    is unset; a one-line warning where it is set but not a whole number in [0, MAX_MACHINE_JOBS]: then ignored)."""
    raw = environ.get(MACHINE_JOBS_ENV)
    if raw is None:
        return None, None
    count = whole_number(raw, 0, MAX_MACHINE_JOBS)
    if count is None:
        return None, (f"{MACHINE_JOBS_ENV}={raw!r} is not a whole number in [0, {MAX_MACHINE_JOBS:,}]: ignored (it "
                      f"counts the job processes of other workers on this host)")
    return count, None


def lost_seconds(threads: dict, wall_s: float) -> float | None:
    """Seconds of `wall_s` (a run's training) that it lost to other processes, by the module's rule, from
    `ThreadWaits.summary`'s figures: the stepping thread's wait, and the waits of the helpers runnable at least
    RUNNABLE_SHARE of `wall_s`; at most `wall_s`. None where the figures are missing or not finite and positive."""
    if not threads or not (isinstance(wall_s, (int, float)) and 0 < wall_s < math.inf):
        return None
    try:
        pairs = [(float(run), float(wait)) for run, wait in [threads["main"], *threads.get("helpers", [])]]
    except (KeyError, TypeError, ValueError):
        return None
    if not all(0 <= run < math.inf and 0 <= wait < math.inf for run, wait in pairs):
        return None
    (run, lost), helpers = pairs[0], pairs[1:]
    if run + lost < MAIN_SEEN_SHARE * wall_s:
        # The stepping thread runs or waits for every step: figures that miss most of training are statistics this
        # kernel does not keep (all zeros), not an idle machine.
        return None
    lost += sum(wait for run, wait in helpers if counted(run, wait, wall_s))
    return min(lost, wall_s)


def counted(run: float, wait: float, wall_s: float) -> bool:
    """Whether a helper thread's `wait` counts as the run's loss: it was runnable (`run` + `wait` seconds on a CPU or
    waiting for one) at least RUNNABLE_SHARE of `wall_s`."""
    return run + wait >= RUNNABLE_SHARE * wall_s


def counted_helpers(threads: dict, wall_s: float) -> int:
    """How many helper threads of `ThreadWaits.summary`'s figures count (`counted`): more than none means the run's
    own threads may have kept each other waiting (more threads than the cores free to them), not only other
    processes. 0 where the figures cannot be read."""
    try:
        return sum(counted(float(run), float(wait), wall_s) for run, wait in threads.get("helpers", []))
    except (AttributeError, TypeError, ValueError):
        return 0


__all__ = ["TASKS", "RUNNABLE_SHARE", "MAIN_SEEN_SHARE", "MACHINE_JOBS_ENV", "MAX_MACHINE_JOBS", "machine_jobs",
           "read_threads", "ThreadWaits", "lost_seconds", "counted", "counted_helpers"]
