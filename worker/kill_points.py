"""Named steps of publishing a job's result, at which a test can make the worker die (SIGKILL) to prove that no step
loses a result or leaves the queue saying something that did not happen.

`kill_point(name)` does nothing unless the environment variable SPADSCAN_KILL_AT names that step; then the process
kills itself with SIGKILL, as `kill -9` would, with no chance to clean up.
"""

from __future__ import annotations

import os
import signal

ENV = "SPADSCAN_KILL_AT"

PUBLISH_STEPS = ("job-ended", "log-copied", "marked-complete", "result-recorded", "moved-aside", "published",
                 "settled", "finished")
"""A worker publishing a finished job, in order: the job process has ended; its log is copied into the result;
the completion marker is written (last) into the scratch folder; the attempt record names the result folder; an
earlier result folder is moved aside; the scratch folder is renamed into place; the job file is moved to done/ (the
queue's `done`); the attempt record says done."""

RECOVERY_STEPS = ("adopted", "recovered-published")
"""A worker at start-up publishing the complete result a dead worker left in a scratch folder: it has taken the
dead worker's claim over; it has renamed the scratch folder into place (then `settled` and `finished` as above)."""


def kill_point(name: str) -> None:
    """SIGKILL this process here when $SPADSCAN_KILL_AT is `name` (a test hook; a no-op otherwise)."""
    if os.environ.get(ENV) == name:
        os.kill(os.getpid(), signal.SIGKILL)
