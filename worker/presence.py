"""Which workers serve a queue, idle ones included: each running worker keeps a small file of its own under the
queue (`<queue>/workers/<host>-<pid>-<token>.json`), renewed every RENEW_S seconds and removed when it stops.

Without it a worker with nothing to do leaves no trace, and the dashboard and `worker --status` cannot tell an idle
worker from none at all: an operator who finished a scan could not see whether a reconstruction will follow. A file
whose worker was killed stays behind; it counts no more once it is older than three renewals, or at once when its
process is gone from this machine (`holder.holder_gone`), and the next worker to start removes it then, or once it is
a day old wherever its worker ran (a power cut, a machine gone). Its age is the reader's clock against the file
system's, as a claim's is: machines sharing a queue keep their clocks within a few seconds (NTP).
"""

from __future__ import annotations

import json
import math
import secrets
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from spadscan.protocol.atomic_files import write_atomic

from .disk_room import RoomWait, when_text
from .holder import holder_gone
from .jobs import worker_command
from .queue import file_age

WORKERS_DIRNAME = "workers"
"""The folder under the queue that holds the workers' presence files."""
RENEW_S = 10.0
"""Seconds between a worker's renewals of its file: often enough for a page that polls every few seconds, rarely
enough that a queue on a network share is not kept busy by idle workers."""
MISSED_RENEWALS = 3
"""A file not renewed for this many renewals (a killed worker, a lost mount) no longer counts."""
FORGET_S = 86400.0
"""A file (or a temporary one a killed write left) not renewed for this long is removed by the next worker to start,
wherever its worker ran: a machine that rebooted or is gone leaves nobody who could be sure its worker is dead."""


@dataclass
class Presence:
    """What a running worker says of itself. Times are seconds since the epoch (its own clock)."""

    holder: dict
    """Who it is (`Holder.to_dict`): host and pid, and what tells a dead process on this machine."""
    root: str
    """The captures root it watches."""
    started_unix: float
    processes: int
    """Job processes it runs at once."""
    once: bool = False
    """It stops once the queue is drained (`--once`)."""
    running: list[str] = field(default_factory=list)
    """The jobs its processes run now."""
    renew_s: float = RENEW_S
    token: str = field(default_factory=lambda: secrets.token_hex(4))
    """This run's own, in its file's name: two workers with one host name and pid (containers, cloned machines)
    never share a file."""
    room_wait: dict | None = None
    """None, or the wait for room on a full disk during which it claims no job (disk_room.RoomWait.note): exactly
    the keys "mount" (str: where the full filesystem is mounted), "folder" (str: the folder that could not be
    written), "free_bytes" and "need_bytes" (int or None: free when last probed, and free that ends the wait),
    "since_unix" (float), "retry_unix" (float: when it claims again all the same) and "quota" (bool: a full disk
    quota, which the free space does not show), and, where the folder lies under the queue or the captures root,
    "relative_to" ("queue" or "root") and "relative" (str: the folder relative to it, which a reader on another
    machine finds under its own). The file is rewritten when a wait begins and when it ends."""


def presence_path(queue_dir: Path, presence: Presence) -> Path:
    holder = presence.holder
    return Path(queue_dir) / WORKERS_DIRNAME / f"{holder['host']}-{holder['pid']}-{presence.token}.json"


def write_presence(queue_dir: Path, presence: Presence) -> Path:
    """Write (or renew) the worker's file; OSError on a full disk or a read-only queue, for the caller to report."""
    path = presence_path(queue_dir, presence)
    path.parent.mkdir(exist_ok=True)
    return write_atomic(path, json.dumps(asdict(presence), indent=1) + "\n")


def remove_presence(queue_dir: Path, presence: Presence) -> None:
    presence_path(queue_dir, presence).unlink(missing_ok=True)


def present_workers(queue_dir: Path, now: float | None = None, *, tidy: bool = False) -> list[dict]:
    """The workers that serve the queue now: one dict each ({"host", "pid", "root", "started_unix", "processes",
    "once", "running", "room_wait": its wait for room or None (`Presence.room_wait`; None too where the file's is
    damaged), "seen_s": seconds since its last renewal}), the longest running first. A file that cannot be
    read, or whose worker stopped renewing it or is gone from this machine, is left out (`tidy`: and removed when its
    process is known gone or it is FORGET_S old, as are temporary files that old)."""
    return [row for row, _ in _listed(queue_dir, now, tidy)]


def machine_siblings(queue_dir: Path, me: dict, now: float | None = None, *, tidy: bool = False) -> list[dict]:
    """The other workers present (`present_workers`' rows, each with its `processes`) that run on the machine of the
    process `me` (`Holder.to_dict`), and so share its CPU cores: the same running kernel (boot id) where both files
    say one, else the same host name. Containers on one machine share its kernel, whatever their host names; machines
    cloned with one host name do not. `me`'s own process is none of them (its file, or another worker object in it)."""
    return [row for row, holder in _listed(queue_dir, now, tidy)
            if same_machine(holder, me) and not _same_process(holder, me)]


def same_machine(holder: dict, me: dict) -> bool:
    """Whether two holders (`Holder.to_dict`) run on one machine: one boot id where both say one, else one host."""
    boot, mine = str(holder.get("boot_id") or ""), str(me.get("boot_id") or "")
    return boot == mine if boot and mine else str(holder.get("host")) == str(me.get("host"))


def _same_process(holder: dict, me: dict) -> bool:
    return all(str(holder.get(k) or "") == str(me.get(k) or "") for k in ("host", "pid", "boot_id", "pid_ns"))


def _listed(queue_dir: Path, now: float | None, tidy: bool) -> list[tuple[dict, dict]]:
    """(row, holder) of each worker `present_workers` lists, in its order: the row it lists, the file's `holder`."""
    now = time.time() if now is None else now
    folder = Path(queue_dir) / WORKERS_DIRNAME
    try:
        paths = sorted(folder.glob("*.json"))
        if tidy:
            _forget([p for p in folder.glob(".*.tmp") if (file_age(p, now) or 0.0) > FORGET_S])
    except OSError:
        return []
    found = []
    for path in paths:
        row, holder, gone = _present(path, now)
        if row is not None:
            found.append((row, holder))
        elif tidy and gone:
            _forget([path])
    return sorted(found, key=lambda pair: (pair[0]["started_unix"], pair[0]["host"], pair[0]["pid"]))


def _present(path: Path, now: float) -> tuple[dict | None, dict, bool]:
    """(one file's worker as `present_workers` lists it, or None; the file's holder ({} where it is not read);
    whether its worker is certainly gone: its process gone from this machine, or its file FORGET_S old)."""
    try:
        seen_s = file_age(path, now)
        if seen_s is None:
            return None, {}, False  # moved on meanwhile (a worker's own tidy)
        data = json.loads(path.read_text())
        holder = data["holder"]
        renew_s = _positive(data.get("renew_s"), RENEW_S)
        row = {"host": str(holder["host"]), "pid": int(holder["pid"]), "root": str(data.get("root", "")),
               "started_unix": _positive(data.get("started_unix"), 0.0), "processes": int(data.get("processes", 1)),
               "once": bool(data.get("once", False)), "running": [str(j) for j in data.get("running", [])],
               "room_wait": room_wait_of(data.get("room_wait")), "seen_s": round(seen_s, 1)}
        gone = holder_gone({**holder, "pid": row["pid"]}) or seen_s > FORGET_S
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None, {}, False  # moved on meanwhile, or damaged: a damaged file says nothing about a worker
    return (None if gone or seen_s > MISSED_RENEWALS * renew_s else row), holder, gone


def room_wait_of(value) -> dict | None:
    """A presence file's `room_wait` as `Presence.room_wait` says it (exactly its keys), or None where it is none or
    not one (a damaged file, another version's). One that begins ahead of this clock is said all the same: its
    worker waits, whatever the clocks say."""
    wait = RoomWait.from_note(value, skewed=True) if isinstance(value, dict) else None
    return None if wait is None else wait.note()


def _forget(paths) -> None:
    for path in paths:
        try:
            path.unlink(missing_ok=True)
        except OSError:
            pass  # another worker's tidy, or a read-only queue: it counts no more all the same


def workers_line(rows: list[dict], start: str) -> str:
    """One line on the workers present (`present_workers`), for `worker --status`: each one's host, pid, whether it
    runs jobs, since when; with none, that no worker runs and `start`, the command that starts one."""
    if not rows:
        return f"no worker is running on this queue (a worker queues and reconstructs each complete scan): {start}"
    said = []
    for r in rows:
        doing = f"running {', '.join(r['running'])}" if r["running"] else "waiting for scans"
        room = waiting_for_room(r["room_wait"]) if r.get("room_wait") else ""
        if room:
            doing += f"; {room}"
        since = _utc(r["started_unix"])
        said.append(f"{r['host']} pid {r['pid']} ({doing}; since {since}{', until drained' if r['once'] else ''})")
    return ("worker: " if len(rows) == 1 else f"{len(rows)} workers: ") + "; ".join(said)


def waiting_for_room(wait: dict) -> str:
    """What a worker's wait for room (`Presence.room_wait`) is, in a few words, for `worker --status`: where (as
    the worker's own lines say it, `RoomWait.where`) and until when at the latest (a note that cannot be read says
    so). One that begins ahead of this clock is said as it stands: its worker waits all the same."""
    read = RoomWait.from_note(wait, skewed=True)
    if read is None:
        return "waiting for room before claiming a job (its note cannot be read)"
    return f"waiting for room {read.where} before claiming a job, until {when_text(read.retry_unix)} at the latest"


def start_command(root: Path, queue_dir: Path) -> str:
    """The command that starts a worker on `root` (and its queue, when it is not the default one)."""
    return worker_command(root, queue_dir)


def _utc(unix: float) -> str:
    """A time as every line about the workers says it (disk_room.when_text): a damaged file's start, past what the
    clock can name, is 'an unknown time'."""
    return when_text(unix)


def _positive(value, default: float) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0
    return float(value) if ok else default


__all__ = ["WORKERS_DIRNAME", "RENEW_S", "MISSED_RENEWALS", "FORGET_S", "Presence", "presence_path", "write_presence",
           "remove_presence", "present_workers", "machine_siblings", "same_machine", "room_wait_of", "workers_line",
           "waiting_for_room", "start_command"]
