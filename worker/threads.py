"""How many CPU threads each reconstruction may use, so that reconstructions running at once share the cores.

Measured on a 2-core CPU (the `fast` preset, LCSPC sphere): alone on idle cores a second torch thread gains 8-10 %
per step (37 against 40 ms at the coarse level, 49 against 54 ms at the fine one). But OpenMP threads wait for one
another at the end of every one of a step's ~800 small operations, so a thread that loses its core stalls them all:
with another process busy on one core, two threads make a step 2.7 times slower than one (104 against 39 ms); two
reconstructions of two threads each on the two cores run 20 to 40 times slower (780-1,690 ms per step) than two of
one thread each (39-46 ms).

So a CPU reconstruction chooses its threads as it runs (`ThreadGovernor`): it starts with one thread, times its
steps with it and with all the threads it may use, keeps the faster, and tries the other again from time to time
(sooner when its steps suddenly slow down), since other processes come and go.

How its OpenMP threads wait for each other is set before torch starts (`wait_env`), for the job processes and by
`spadscan reconstruct`. A thread that spins while its partner has lost its core takes that core from the partner;
one that sleeps at once pays a wake-up at each of the step's operations. Measured on the 2-core machine (the demo's
goblet, fine level, ms per step), two threads:

| wait                              | idle | one core busy |
|-----------------------------------|------|---------------|
| passive (`OMP_WAIT_POLICY=PASSIVE`) | 68   | 75            |
| spin 3,000 / 10,000 / 30,000 / 100,000 (`GOMP_SPINCOUNT`) | 62 / 55 / 50 / 51 | 345 (30,000) |
| spin without end (`ACTIVE`)       | 52   |               |
| one thread                        | 66   | 65            |

So a run whose threads the governor chooses spins briefly (30,000, about a third of a millisecond): idle, two threads
then beat one by a quarter; busy, the governor has gone to one thread, which never waits. A run whose threads are
fixed (`--threads`, the user's OMP_NUM_THREADS) has no governor to leave a stalled pair, so its threads wait
passively.
"""

from __future__ import annotations

import math
import os
import statistics
from typing import Callable, Mapping

from spadscan.protocol.errors import ConfigError

from .env_number import whole_number

ENV = "OMP_NUM_THREADS"
"""Read by torch and by numpy's BLAS when they start: how a parent process sets its children's threads."""
WAIT_ENV = "OMP_WAIT_POLICY"
"""How idle OpenMP threads wait: PASSIVE (sleep) or ACTIVE (spin). Read once, when torch's OpenMP runtime starts."""
SPIN_ENV = "GOMP_SPINCOUNT"
"""GNU OpenMP's spins before a waiting thread sleeps (torch's CPU builds use GNU OpenMP): a user who sets it, or
OMP_WAIT_POLICY, has chosen, and neither is touched."""
SHORT_SPIN = "30000"
"""Spins of a run whose threads the governor chooses: about a third of a millisecond, where two threads reach the
speed of spinning without end on idle cores (the module's table)."""
ADAPT_ENV = "SPADSCAN_ADAPT_THREADS"
"""Set to 1 by the worker for jobs whose OMP_NUM_THREADS is its default share of the cores (not a user's choice): the
job may then use fewer threads when that is faster (`ThreadGovernor`)."""


MAX_THREADS = 1024
"""The most CPU threads a run may be given (--threads, a config, OMP_NUM_THREADS)."""


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
    """`threads` as given on a command line or in a config: an integer in [1, MAX_THREADS]."""
    if not (isinstance(threads, int) and not isinstance(threads, bool) and 1 <= threads <= MAX_THREADS):
        raise ConfigError(f"threads {threads} must be an integer in [1, {MAX_THREADS}]")
    return threads


def inherited_threads(environ) -> tuple[int | None, str | None]:
    """(the threads `environ`'s OMP_NUM_THREADS asks for, or None when unset or unusable; a warning when it is set
    but not a whole number >= 1, which torch would reject or misread)."""
    raw = environ.get(ENV)
    if not raw or not raw.strip():
        return None, None
    threads = whole_number(raw, 1, MAX_THREADS)
    if threads is None:
        return None, f"{ENV}={raw!r} in the worker's environment is not a whole number in [1, {MAX_THREADS}]: ignored"
    return threads, None


def oversubscribed(processes: int, threads: int, cores: int | None = None, others: int = 0) -> str | None:
    """A one-line warning when this worker's `processes` jobs and the `others` job processes of the other workers on
    its machine, each of `threads` threads, ask for more threads than there are `cores` (default: this machine's),
    else None. With others, the line counts them apart and its advice speaks to every worker there."""
    cores = cores or machine_cores()
    total = processes + others
    if total * threads <= cores:
        return None
    if threads > 1:
        advice = (f"OpenMP threads that lose their core stall each other, each step 20-40x slower; use --threads "
                  f"{max(1, cores // total)}{' in each worker' if others else ''}")
    elif others:
        advice = (f"the jobs take turns on the cores, each run slower; stop a worker, or run one worker with "
                  f"--processes {one_worker_processes(total, cores)}")
    else:
        advice = f"the jobs take turns on the cores; --processes {cores} runs as many at once as there are cores"
    where = f" on this host ({processes} of this worker's, {others} of other workers')" if others else ""
    return (f"{total} job process(es){where} x {threads} CPU thread(s) = {total * threads} threads on "
            f"{cores} cores: {advice}")


def one_worker_processes(total: int, cores: int) -> int:
    """The --processes of one worker that does what workers running `total` job processes on a host of `cores` do,
    as their lines advise it: as many, but no more than there are cores (more take turns on them)."""
    return max(1, min(total, cores))


def wait_env(environ: Mapping[str, str], adapting: bool) -> dict[str, str]:
    """How OpenMP threads wait, as variables to add to the environment before torch loads: a short spin
    ({GOMP_SPINCOUNT: SHORT_SPIN}) when the run's threads are `adapting` (`ThreadGovernor`), else passive
    ({OMP_WAIT_POLICY: PASSIVE}); nothing when `environ` already says (OMP_WAIT_POLICY or GOMP_SPINCOUNT)."""
    if environ.get(WAIT_ENV) or environ.get(SPIN_ENV):
        return {}
    return {SPIN_ENV: SHORT_SPIN} if adapting else {WAIT_ENV: "PASSIVE"}


def threads_fixed(threads: int | None, environ: Mapping[str, str]) -> bool:
    """Whether a run's CPU threads are a choice to keep (`--threads`, or a user's OMP_NUM_THREADS) rather than a
    ceiling to adapt under (`ThreadGovernor`)."""
    if threads is not None:
        return True
    return bool(environ.get(ENV, "").strip()) and environ.get(ADAPT_ENV) != "1"


class ThreadGovernor:
    """Chooses between `most` CPU threads and one, step by step, by the measured step time.

    Feed it every step's wall seconds (`step_done`); it calls `set_threads(n)` when it switches. It starts with one
    thread (`set_threads(1)` at once): one thread never stalls, while `most` of them beside a busy process would stall
    every step until the first probe (measured: 14 steps of 1.1 s each against 0.07 s, half a 60 s budget's
    training); after `warmup` steps it times `block` steps of the current choice, then up to `block` of the other (a
    probe, cut short at the first step over `abort` times the current median: a stalled probe costs one step), and
    keeps the faster by medians (many threads only when they are `margin` faster: one thread never stalls). It holds
    its choice for `hold` steps, twice as long after each probe that confirms it (at most `max_hold`), and long
    enough that probes take at most `probe_share` of the time (a stalled probe step may cost 40 ordinary ones); it
    probes again at once when two steps of many threads take over `stall` times their median (a competitor just
    started)."""

    def __init__(self, most: int, set_threads: Callable[[int], None], *, warmup: int = 5, block: int = 8,
                 hold: int = 40, max_hold: int = 640, abort: float = 2.5, stall: float = 3.0,
                 margin: float = 0.03, probe_share: float = 0.05):
        if not (isinstance(most, int) and most >= 2):
            raise ConfigError(f"a thread governor needs at least 2 threads to choose from, got {most}")
        self.most, self.set_threads = most, set_threads
        self.warmup, self.block, self.abort, self.stall, self.margin = warmup, block, abort, stall, margin
        self.probe_share = probe_share
        self.hold0, self.max_hold, self.hold = hold, max_hold, hold
        self.current = 1
        set_threads(1)
        self.phase, self.left = "warmup", warmup
        self.times: list[float] = []
        self.medians: dict[int, float] = {}
        self.steps_by_threads: dict[int, int] = {}
        self.probes = self.switches = 0
        self._chosen = 1

    @property
    def threads(self) -> int:
        """The threads the next step runs with."""
        return self.current

    def _use(self, n: int) -> None:
        if n != self.current:
            self.current = n
            self.set_threads(n)

    def step_done(self, seconds: float) -> None:
        """Count one step that took `seconds` of wall time with `self.threads` threads."""
        self.steps_by_threads[self.current] = self.steps_by_threads.get(self.current, 0) + 1
        if not math.isfinite(seconds) or seconds < 0:
            return
        self.left -= 1
        if self.phase == "warmup":
            if self.left <= 0:
                self._start("measure", self.block)
        elif self.phase == "measure":
            self.times.append(seconds)
            if self.left <= 0:
                self.medians[self.current] = statistics.median(self.times)
                self._probe()
        elif self.phase == "probe":
            self.times.append(seconds)
            base = self.medians[self._chosen]
            if seconds > self.abort * base or self.left <= 0:
                self.medians[self.current] = statistics.median(self.times)
                self._decide()
        else:  # hold
            self.times.append(seconds)
            base = self.medians.get(self.current)
            recent = self.times[-2:]
            stalled = self.current > 1 and base and len(recent) == 2 and min(recent) > self.stall * base
            if stalled or self.left <= 0:
                self.medians[self.current] = statistics.median(recent if stalled else self.times[-self.block:])
                self._probe()

    def _start(self, phase: str, steps: int) -> None:
        self.phase, self.left, self.times = phase, steps, []

    def _probe(self) -> None:
        self._chosen = self.current
        self.probes += 1
        self._use(1 if self.current > 1 else self.most)
        self._start("probe", self.block)

    def _decide(self) -> None:
        many, one = self.medians.get(self.most), self.medians.get(1)
        best = self.most if (many is not None and one is not None and many < (1 - self.margin) * one) else 1
        if best == self._chosen:
            self.hold = min(self.max_hold, 2 * self.hold)
        else:
            self.hold = self.hold0
            self.switches += 1
        # A probe costs at most `probe_share` of the time: a stalled one (seconds a step) is followed by a long hold.
        probe_s, best_s = sum(self.times), self.medians.get(best) or 0.0
        hold = self.hold if best_s <= 0 else max(self.hold, math.ceil(probe_s / (self.probe_share * best_s)))
        self._use(best)
        self._start("hold", hold)

    def summary(self) -> dict:
        """JSON-able: the ceiling, the threads now, steps run with each count, probes and switches, the last
        median step seconds of each count."""
        return {"most": self.most, "now": self.current, "probes": self.probes, "switches": self.switches,
                "steps_by_threads": {str(k): v for k, v in sorted(self.steps_by_threads.items())},
                "median_step_s": {str(k): v for k, v in sorted(self.medians.items())}}


__all__ = ["ENV", "WAIT_ENV", "SPIN_ENV", "SHORT_SPIN", "ADAPT_ENV", "wait_env", "threads_fixed", "ThreadGovernor",
           "machine_cores", "threads_per_job", "check_threads", "inherited_threads", "oversubscribed",
           "one_worker_processes"]
