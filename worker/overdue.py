"""When the worker stops a job process that has run far past its time budget.

A job keeps its own budget (it stops training in time for its mesh, metrics and pictures, and its metrics stop on a
deadline): a process still running long after it has hung, stopped (SIGSTOP), or waits on a file that never answers
(a hung network mount). Nothing in it will end it, and the queue behind it would wait for good, its heartbeat fresh
and `--status` saying it runs. The worker stops it as it stops a job on shutdown (SIGTERM, then SIGKILL after the
grace period) and records a crash that names why; the queue retries it as any crash.

The limit is far from a slow run's: twice the budget and five minutes more (a job on a busy machine ends its last
stages late by seconds to tens of seconds). A job without a budget (a step count only) is never stopped: no limit
says how long it should take; nor is a live job while it follows its scan (its budget bounds its final run, from the
scan's end). An ordinary job's time is measured on the monotonic clock: a machine suspended for an hour does not stop
every job on waking.
"""

from __future__ import annotations

import math

from .job_progress import clock

OVERDUE_FACTOR = 2.0
"""A job is overdue past this many times its budget, plus OVERDUE_GRACE_S."""
OVERDUE_GRACE_S = 300.0


def overdue_limit_s(budget_s: float) -> float:
    """Seconds from the budget's start after which a job with `budget_s` seconds is stopped."""
    return OVERDUE_FACTOR * budget_s + OVERDUE_GRACE_S


def overdue_reason(budget: tuple[float, float] | None, now: float) -> str | None:
    """Why a running job is stopped at `now` (seconds, on the clock `budget`'s start is read on), or None while it is
    not overdue. `budget`: (budget_s, when it started counting), as `job_progress.claim_budget` gives it (None: no
    budget known)."""
    if budget is None:
        return None
    budget_s, start = budget
    spent = now - start
    if not (math.isfinite(spent) and spent > overdue_limit_s(budget_s)):
        return None
    return (f"stopped by the worker {clock(spent - budget_s)} past its {clock(budget_s)} budget: its process had "
            f"not ended in {OVERDUE_FACTOR:g} times its budget and {clock(OVERDUE_GRACE_S)} more (hung, stopped, or "
            f"waiting on a file that does not answer)")


__all__ = ["OVERDUE_FACTOR", "OVERDUE_GRACE_S", "overdue_limit_s", "overdue_reason"]
