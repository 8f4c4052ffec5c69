"""How many CPU threads each reconstruction may use, so that reconstructions running at once share the cores.

Measured on a 2-core CPU (the `fast` preset, LCSPC sphere): alone on idle cores a second torch thread gains 8-10 %
per step (37 against 40 ms at the coarse level, 49 against 54 ms at the fine one). But OpenMP threads wait for one
another at the end of every one of a step's ~800 small operations, so a thread that loses its core stalls them all:
with another process busy on one core, two threads make a step 2.7 times slower than one (104 against 39 ms); two
reconstructions of two threads each on the two cores run 20 to 40 times slower (780-1,690 ms per step) than two of
one thread each (39-46 ms).
"""

from __future__ import annotations

import os

from spadscan.protocol.errors import ConfigError

ENV = "OMP_NUM_THREADS"
"""Read by torch and by numpy's BLAS when they start: how a parent process sets its children's threads."""


def machine_cores() -> int:
    """Logical CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not on Linux
        return max(1, os.cpu_count() or 1)


def threads_per_job(processes: int, cores: int | None = None) -> int:
    """Threads for each of `processes` reconstructions running at once: the cores shared out, at least one."""
    if not (isinstance(processes, int) and processes >= 1):
        raise ConfigError(f"processes {processes} must be an integer >= 1")
    return max(1, (cores or machine_cores()) // processes)


def check_threads(threads) -> int:
    """`threads` as given on a command line or in a config: an integer in [1, 1024]."""
    if not (isinstance(threads, int) and not isinstance(threads, bool) and 1 <= threads <= 1024):
        raise ConfigError(f"threads {threads} must be an integer in [1, 1024]")
    return threads


def inherited_threads(environ) -> tuple[int | None, str | None]:
    """(the threads `environ`'s OMP_NUM_THREADS asks for, or None when unset or unusable; a warning when it is set
    but not a whole number >= 1, which torch would reject or misread)."""
    raw = environ.get(ENV)
    if not raw or not raw.strip():
        return None, None
    try:
        return check_threads(int(raw)), None
    except (ValueError, ConfigError):
        return None, f"{ENV}={raw!r} in the worker's environment is not a whole number in [1, 1024]: ignored"


def oversubscribed(processes: int, threads: int, cores: int | None = None) -> str | None:
    """A one-line warning when `processes` jobs of `threads` threads each ask for more threads than there are
    `cores` (default: this machine's), else None."""
    cores = cores or machine_cores()
    if processes * threads <= cores:
        return None
    if threads > 1:
        advice = (f"OpenMP threads that lose their core stall each other, each step 20-40x slower; use --threads "
                  f"{max(1, cores // processes)}")
    else:
        advice = f"the jobs take turns on the cores; --processes {cores} runs as many at once as there are cores"
    return (f"{processes} job process(es) x {threads} CPU thread(s) = {processes * threads} threads on "
            f"{cores} cores: {advice}")


__all__ = ["ENV", "machine_cores", "threads_per_job", "check_threads", "inherited_threads", "oversubscribed"]
