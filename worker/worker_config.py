"""How a worker runs (`spadscan worker`): one dataclass with a docstring per setting, checked before any job starts."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from spadscan.protocol.errors import ConfigError

from .threads import (ADAPT_ENV, ENV as THREADS_ENV, check_threads, inherited_threads, machine_cores,
                      oversubscribed, threads_per_job, wait_env)
from .watcher import JobOptions, check_root


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
    among `processes`, at least one. Jobs that together ask for more threads than there are cores stall each other
    (threads.py: 20-40x slower per step with two 2-thread jobs on 2 cores)."""

    def job_env(self, environ: Mapping[str, str] | None = None) -> dict[str, str]:
        """Environment variables the job processes get on top of the worker's own (`environ`, default os.environ):
        the threads per job, how their OpenMP threads wait (threads.py), then `child_env`. Threads the worker
        shared out itself are a ceiling the job may go under when fewer are faster (ADAPT_ENV), and wait with a
        short spin; --threads and the worker's own OMP_NUM_THREADS are kept as given, and wait passively."""
        environ = os.environ if environ is None else environ
        env: dict[str, str] = {}
        if self.threads is not None:
            env[THREADS_ENV] = str(self.threads)
        elif inherited_threads(environ)[0] is None:  # unset, or a value torch cannot use: replaced
            env[THREADS_ENV] = str(threads_per_job(self.processes))
            env[ADAPT_ENV] = "1"
        env.update(wait_env(environ, adapting=ADAPT_ENV in env))
        return {**env, **(self.child_env or {})}

    def job_threads(self, environ: Mapping[str, str] | None = None) -> int | None:
        """CPU threads each job process gets (None when child_env sets something that is not a number)."""
        environ = os.environ if environ is None else environ
        value = self.job_env(environ).get(THREADS_ENV) or environ.get(THREADS_ENV, "")
        try:
            return int(value)
        except ValueError:
            return None

    def threads_warnings(self, environ: Mapping[str, str] | None = None) -> list[str]:
        """One-line warnings about the threads per job: an unusable OMP_NUM_THREADS that was ignored, and jobs that
        together ask for more threads than there are cores."""
        environ = os.environ if environ is None else environ
        warnings = []
        bad = inherited_threads(environ)[1]
        if bad and self.threads is None and THREADS_ENV not in (self.child_env or {}):
            warnings.append(bad)
        threads = self.job_threads(environ)
        over = oversubscribed(self.processes, threads) if threads else None
        if over:
            warnings.append(over)
        return warnings

    def threads_note(self, environ: Mapping[str, str] | None = None) -> str:
        """How many CPU threads each job gets and why, for the worker's start-up line."""
        environ = os.environ if environ is None else environ
        value = self.job_env(environ).get(THREADS_ENV) or environ.get(THREADS_ENV)
        if THREADS_ENV in (self.child_env or {}):
            why = "set by child_env"
        elif self.threads is not None:
            why = "set by --threads"
        elif inherited_threads(environ)[0] is not None:
            why = "the worker's own environment"
        else:
            why = f"{machine_cores()} cores shared out among {self.processes} job process(es)"
        return f"{value} CPU threads per job ({THREADS_ENV}={value}: {why})"

    def check(self) -> "WorkerConfig":
        if not (isinstance(self.processes, int) and 1 <= self.processes <= 256):
            raise ConfigError(f"processes {self.processes} must be an integer in [1, 256]")
        for key in ("poll_s", "lease_s", "stop_grace_s"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and 0 < v < 1e6):
                raise ConfigError(f"{key.replace('_s', '')} {v} s must be > 0")
        if self.threads is not None:
            check_threads(self.threads)
        self.options.check()
        check_root(self.root)
        return self
