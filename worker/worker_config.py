"""How a worker runs (`spadscan worker`): one dataclass with a docstring per setting, checked before any job starts."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from spadscan.protocol.errors import ConfigError

from .cpu_wait import MACHINE_JOBS_ENV
from .threads import (ADAPT_ENV, ENV as THREADS_ENV, check_threads, inherited_threads, machine_cores,
                      one_worker_processes, oversubscribed, threads_per_job, wait_env)
from .watcher import JobOptions, check_root

MAX_SECONDS = 1e6
"""The worker's times (poll, lease, stop grace) are under this many seconds (11 days): a larger one, or inf, is a
typo, not a wish."""


def machine_job_processes(siblings: list[dict]) -> int:
    """Job processes the other workers on this machine (`presence.machine_siblings` rows) may run at once: each
    one's `processes` (at least the jobs it runs now, at most 256, as `check` allows), whether it runs them now or
    not. A job's threads are fixed for its whole run, and an idle worker may claim a job at its next look: counted
    only while they run, two workers that claim at one poll (two scans queued together) would both find the other
    idle, its presence not yet renewed, and take every core each."""
    return sum(max(1, len(r.get("running") or []), min(int(r.get("processes") or 1), 256)) for r in siblings)


@dataclass
class WorkerConfig:
    """How a worker runs. Times in seconds."""

    root: Path
    """Captures root: its children are scan folders."""
    processes: int = 1
    """Jobs run at once (one child process each)."""
    options: JobOptions = field(default_factory=JobOptions)
    """Preset, budget, device, seed of the jobs this worker queues."""
    options_given: tuple[str, ...] | None = None
    """The job options (jobs.CHANGEABLE) that were asked for (given on the command line); queued jobs whose own
    values of these differ are named at start-up and when queued again, since they keep their own. None: all of them."""
    queue_dir: Path | None = None
    """Queue folder; default `<root>/.queue`."""
    poll_s: float = 2.0
    """How often the root is scanned and the queue looked at."""
    lease_s: float = 60.0
    """A job whose holder has not renewed its lease for this long is taken over by another worker."""
    max_attempts: int = 3
    """A job whose process dies or whose worker dies is retried until it has been tried this many times."""
    once: bool = False
    """Queue what is there, run until no job is queued or running, then exit."""
    stop_grace_s: float = 10.0
    """On stop, children get SIGTERM and this long to exit before SIGKILL."""
    recon: str | None = None
    """`module:function` replacing the reconstruction (tests only; not on the command line)."""
    child_env: dict[str, str] | None = None
    """Extra environment variables for the job processes (they win over `threads`)."""
    threads: int | None = None
    """CPU threads per job, given to each job process as OMP_NUM_THREADS (read by torch and numpy's BLAS at start).
    None: the worker's own OMP_NUM_THREADS when it has one (the user chose), else the machine's cores shared out
    among the job processes of this worker (`processes`) and of the other workers present on its machine (`others`
    of the methods below, `machine_job_processes`), at least one. Jobs that together ask for more threads than
    there are cores stall each other (threads.py: 20-40x slower per step with two 2-thread jobs on 2 cores)."""

    def job_env(self, environ: Mapping[str, str] | None = None, others: int = 0) -> dict[str, str]:
        """Environment variables the job processes get on top of the worker's own (`environ`, default os.environ):
        the threads per job, how their OpenMP threads wait (threads.py), then `child_env`. Threads the worker
        shared out itself (among its `processes` and the `others` job processes of the other workers on its
        machine) are a ceiling the job may go under when fewer are faster (ADAPT_ENV), and wait with a short spin;
        --threads and the worker's own OMP_NUM_THREADS are kept as given, and wait passively. The `others` are
        named to the job too (MACHINE_JOBS_ENV; replaced by 0 where the worker's own environment has one): a busy
        warning at its end then knows that other workers' jobs may have held the cores its threads waited for."""
        environ = os.environ if environ is None else environ
        env: dict[str, str] = {}
        if self.threads is not None:
            env[THREADS_ENV] = str(self.threads)
        elif inherited_threads(environ)[0] is None:  # unset, or a value torch cannot use: replaced
            env[THREADS_ENV] = str(threads_per_job(self.processes + others))
            env[ADAPT_ENV] = "1"
        env.update(wait_env(environ, adapting=ADAPT_ENV in env))
        if others or MACHINE_JOBS_ENV in environ:
            env[MACHINE_JOBS_ENV] = str(others)
        return {**env, **(self.child_env or {})}

    def job_threads(self, environ: Mapping[str, str] | None = None, others: int = 0) -> int | None:
        """CPU threads each job process gets (None when child_env sets something that is not a number)."""
        environ = os.environ if environ is None else environ
        value = self.job_env(environ, others).get(THREADS_ENV) or environ.get(THREADS_ENV, "")
        try:
            return int(value)
        except ValueError:
            return None

    def threads_warnings(self, environ: Mapping[str, str] | None = None, others: int = 0) -> list[str]:
        """One-line warnings about the threads per job: an unusable OMP_NUM_THREADS that was ignored, and jobs that
        together ask for more threads than there are cores (this worker's, and the `others` job processes of the
        other workers on its machine, taken to run as many threads each)."""
        environ = os.environ if environ is None else environ
        warnings = []
        bad = inherited_threads(environ)[1]
        if bad and self.threads is None and THREADS_ENV not in (self.child_env or {}):
            warnings.append(bad)
        threads = self.job_threads(environ, others)
        over = oversubscribed(self.processes, threads, others=others) if threads else None
        if over:
            warnings.append(over)
        return warnings

    def threads_note(self, environ: Mapping[str, str] | None = None, others: int = 0) -> str:
        """How many CPU threads each job gets and why, for the worker's start-up line (`others`: the job processes
        of the other workers on its machine, among which the cores are shared out too)."""
        environ = os.environ if environ is None else environ
        value = self.job_env(environ, others).get(THREADS_ENV) or environ.get(THREADS_ENV)
        if THREADS_ENV in (self.child_env or {}):
            why = "set by child_env"
        elif self.threads is not None:
            why = "set by --threads"
        elif inherited_threads(environ)[0] is not None:
            why = "the worker's own environment"
        else:
            why = f"{machine_cores()} cores shared out among {self.processes + others} job process(es)"
        return f"{value} CPU threads per job ({THREADS_ENV}={value}: {why})"

    def siblings_line(self, siblings: list[dict], environ: Mapping[str, str] | None = None,
                      host: str | None = None, threads_said: bool = False) -> str:
        """One line on the other workers on this machine (`presence.machine_siblings` rows) and the CPU threads
        each job gets with them: said when the worker starts beside them and when they change at a job's start.
        `host`: this machine's host name (a sibling with another, in a container, is named with its own). With
        none, the threads the jobs get alone. `threads_said`: the line before it says the threads per job (the
        worker's start-up line), which this one then does not say again. Threads the user fixed are kept: the
        line says how many run on the host's cores in all."""
        environ = os.environ if environ is None else environ
        others = machine_job_processes(siblings)
        note = self.threads_note(environ, others)
        if not siblings:
            return f"no other worker runs on this host now: {note}"
        who = "another worker runs" if len(siblings) == 1 else f"{len(siblings)} other workers run"
        names = ", ".join(f"pid {r['pid']}" if r["host"] == host else f"{r['host']} pid {r['pid']}"
                          for r in siblings)
        total, cores = self.processes + others, machine_cores()
        threads = self.job_threads(environ, others)
        if self.threads_shared(environ):
            said = ", counted in the threads per job above" if threads_said else f": {note}"
        else:
            in_all = (f"{total} job process(es) x {threads} CPU thread(s) = {total * threads} threads on {cores} cores"
                      if threads else f"{total} job process(es) share {cores} cores")
            said = f": the threads per job above kept; {in_all}" if threads_said else f": {note}, kept; {in_all}"
        return (f"{who} on this host ({names}, {others} job process(es)){said}; one worker with --processes "
                f"{one_worker_processes(total, cores)} does the same with less: one process watching the root and "
                f"the queue, not {len(siblings) + 1}")

    def threads_shared(self, environ: Mapping[str, str] | None = None) -> bool:
        """Whether the job's threads are the cores shared out by the worker (not --threads, the worker's own
        OMP_NUM_THREADS or child_env's: kept whatever other workers run)."""
        environ = os.environ if environ is None else environ
        return ADAPT_ENV in self.job_env(environ) and THREADS_ENV not in (self.child_env or {})

    def check(self) -> "WorkerConfig":
        if not (isinstance(self.processes, int) and 1 <= self.processes <= 256):
            raise ConfigError(f"processes {self.processes} must be an integer in [1, 256]")
        for key in ("poll_s", "lease_s", "stop_grace_s"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and 0 < v < MAX_SECONDS):
                raise ConfigError(f"{key.replace('_s', '')} {v} s must be a finite number of seconds over 0 and "
                                  f"under {MAX_SECONDS:g}")
        if self.threads is not None:
            check_threads(self.threads)
        self.options.check()
        check_root(self.root)
        return self
