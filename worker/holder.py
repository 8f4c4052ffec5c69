"""Who holds a claim on a queued job, and whether that process still exists.

The queue (queue.py) records a `Holder` with every claim. A lease normally expires only when its holder stops
renewing it, which takes a whole lease period; `holder_gone` lets a worker on the same machine see at once that the
holder has died, so its job is taken over without that wait and its partial result removed. The test only answers
True when it is sure: a process on another machine (or another boot or pid namespace) is never judged, and a reused
pid is told apart by the process's start time.
"""

from __future__ import annotations

import os
import socket
from dataclasses import asdict, dataclass


def _read(path: str) -> str:
    try:
        with open(path) as f:
            return f.read().strip()
    except OSError:
        return ""


def _pid_start(pid: int) -> str:
    """Start time of a process in clock ticks since boot ('' when unknown): tells a reused pid apart."""
    stat = _read(f"/proc/{pid}/stat")
    return stat.rsplit(")", 1)[1].split()[19] if ")" in stat else ""


def _pid_namespace() -> str:
    try:
        return os.readlink("/proc/self/ns/pid")
    except OSError:
        return ""


@dataclass(frozen=True)
class Holder:
    """Who holds a lease: a process, named so that another process can tell whether it still exists.

    Two processes can only judge each other's liveness on one machine (same host name, boot and pid namespace);
    elsewhere the lease's expiry decides.
    """

    host: str
    pid: int
    boot_id: str = ""
    pid_ns: str = ""
    pid_start: str = ""

    @classmethod
    def current(cls) -> "Holder":
        return cls.of_pid(os.getpid())

    @classmethod
    def of_pid(cls, pid: int) -> "Holder":
        """Process `pid` of this machine (a job process the worker started, say)."""
        return cls(socket.gethostname(), pid, _read("/proc/sys/kernel/random/boot_id"), _pid_namespace(),
                   _pid_start(pid))

    def to_dict(self) -> dict:
        return asdict(self)

    def describe(self) -> dict:
        return {"host": self.host, "pid": self.pid}


def holder_alive(data: dict) -> bool:
    """True only when `data` (Holder.to_dict) names a process on this machine that still exists."""
    return _here(data) is not None and not holder_gone(data)


def _here(data: dict) -> Holder | None:
    """`data` as a Holder when it names a process on this machine (same host, boot and pid namespace), else None."""
    me = Holder.current()
    try:
        h = Holder(**data)
    except TypeError:
        return None
    if (h.host, h.boot_id, h.pid_ns) != (me.host, me.boot_id, me.pid_ns) or not h.boot_id:
        return None
    return h


def holder_gone(data: dict) -> bool:
    """True only when `data` (Holder.to_dict) names a process on this machine that no longer exists."""
    h = _here(data)
    if h is None:
        return False
    try:
        os.kill(h.pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        pass  # it exists, under another user
    start = _pid_start(h.pid)
    if start and h.pid_start and start != h.pid_start:
        return True  # the pid was reused by a newer process
    # A zombie has exited but is not yet reaped by its parent: it holds nothing.
    stat = _read(f"/proc/{h.pid}/stat")
    return ")" in stat and stat.rsplit(")", 1)[1].split()[0] == "Z"
