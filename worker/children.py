"""A job's child process, as the worker sees it: how it is started, how it is signalled, and how its exit reads.

Each job runs in `python -m spadscan.worker.jobs` (its own process: torch, memory and crashes stay there), in a
process group of its own so that the worker can stop it together with any helpers it started.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

from spadscan.protocol.child_command import module_command

from .jobs import EXIT_CRASH, Job
from .queue import Claim


@dataclass
class Child:
    """A running job: its claim, its process, and the files it writes (scratch result, outcome, log)."""

    claim: Claim
    proc: asyncio.subprocess.Process
    scratch: Path
    outcome: Path
    log: Path
    wait: asyncio.Task
    last_beat: float = field(default_factory=time.monotonic)
    spawned: float = field(default_factory=time.monotonic)
    """When its process was started (time.monotonic(): a clock that a suspend or a clock step does not move on)."""
    stopped_why: str | None = None
    """Why the worker stopped it while it ran (`overdue.overdue_reason`): its crash record says this, not its signal."""
    kill_at: float | None = None
    """When a stopped child not yet gone is sent SIGKILL (time.monotonic())."""


async def spawn_job(job: Job, root: Path, scratch: Path, outcome: Path, log: Path, *, recon: str | None,
                    extra_env: dict[str, str] | None, preface: list[str] | None = None,
                    queue: Path | None = None) -> asyncio.subprocess.Process:
    """Start the process that runs `job` into `scratch`, its output going to `log`, after the worker's `preface`
    lines (each as `spadscan worker: LINE`): what the job's own output cannot know, such as the other workers it
    shares the machine's cores with. `queue`: the queue the job was claimed from (None: the root's own), which the
    command its result records to run it again names."""
    cmd = module_command("spadscan.worker.jobs", "--job", json.dumps(job.to_dict()), "--root", root, "--out", scratch,
                         "--outcome", outcome, "--parent-pid", os.getpid())
    if queue is not None:
        cmd += ["--queue", str(queue)]
    if recon:
        cmd += ["--recon", recon]
    env = {**os.environ, **(extra_env or {})}
    with open(log, "wb") as logf:
        for line in preface or []:
            logf.write(f"spadscan worker: {line}\n".encode("utf-8", "backslashreplace"))
        logf.flush()  # the job's output follows, written through its own descriptor's offset
        # A session of its own: a Ctrl-C at the terminal reaches the worker, which then stops its children.
        return await asyncio.create_subprocess_exec(*cmd, stdin=asyncio.subprocess.DEVNULL, stdout=logf,
                                                    stderr=asyncio.subprocess.STDOUT, env=env,
                                                    start_new_session=True)


def kill_group(proc: asyncio.subprocess.Process, sig: int) -> None:
    """Signal a child's whole process group (it may have started helpers of its own)."""
    if proc.returncode is not None:
        return
    try:
        os.killpg(proc.pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def exit_reason(rc: int | None) -> str:
    if rc is None:
        return "job process vanished"
    if rc < 0:
        try:
            name = signal.Signals(-rc).name
        except ValueError:
            name = f"signal {-rc}"
        return f"job process killed by {name}"
    if rc == EXIT_CRASH:
        return "job process crashed"
    return f"job process exited with code {rc}"
