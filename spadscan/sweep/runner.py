"""Running a sweep's points on Dask distributed: an embedded LocalCluster, or the workers of an existing scheduler.

Each point is one Dask task (`dask_point`), one at a time per worker process, one torch thread each. The worker
writes the point's result into DIR/points/ itself, so a result survives whatever happens to this client. When a
worker dies mid-point (killed, out of memory, its machine gone), the scheduler hands its task to another worker
(Dask retries a task whose worker died up to `distributed.scheduler.allowed-failures` times, 3 by default); a
point that kills that many workers is recorded as failed, with how its last worker ended where that is known: only
a worker's nanny (its parent process) learns the exit status, and the embedded cluster's nannies report it
(`ExitNotingNanny`), so that a point there says which signal ended its worker, or its exit code, or that the nanny
itself stopped it for using more than its memory limit (each of the embedded cluster's workers may use an equal share
of the machine's memory); a scheduler's workers do not, and a point there says that its worker died. Workers report
each point's start and stages as Dask events, which this client writes to DIR/log.jsonl. Every sweep on a scheduler
shares the events' topic: each event names its sweep's folder, and a client logs only its own folder's.

A point on a CUDA device asks for the worker resource GPU=1: start GPU workers with `--resources GPU=1`
(one per GPU); an embedded cluster gives each of its workers one.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import secrets
import signal
import sys
import threading
import time
from concurrent.futures import CancelledError
from dataclasses import dataclass, field
from multiprocessing import resource_tracker
from typing import Callable

from dask.utils import format_bytes
from distributed import Client, KilledWorker, LocalCluster, Nanny, as_completed, get_worker, system
from distributed.comm import connect
from distributed.core import Status
from distributed.utils import silence_logging_cmgr
from tqdm import tqdm

import spadscan
from spadscan.protocol.errors import ConfigError, SpadscanError

from .checks import check_workers, local_device
from .fingerprint import Digests, Expected, code_digest
from .plan import Plan, PointTask
from .point import run_point
from .store import SweepDir, warning_count

EVENT_TOPIC = "spadscan-sweep"
DEVICES = ("cpu", "cuda", "auto")
CONNECT_TIMEOUT_S = 15
"""How long --scheduler's address has to answer as a Dask scheduler (connection and Dask's handshake together): a
port that accepts and then says nothing (an HTTP server such as the dashboard's, 8787) would otherwise be waited on
for ever. The connection itself gets CONNECT_SHARE of it, so that a port where nothing listens is told apart."""
CONNECT_SHARE = 2 / 3
RESULTS_EVERY_S = 10.0
"""results.csv is gathered at once when the first point finishes, then at most this often while points finish (it
reads every point's file): a point that finishes sooner is gathered when the time is up, not only when another point
finishes (which can take hours). And at the end."""
POLL_S = 0.1
"""How often the client looks for finished points while it waits (as often as Dask's own `as_completed` does)."""
EXIT_TOPIC = "spadscan-worker-exit"
"""The topic on which the embedded cluster's nannies report how a worker process ended (`ExitNotingNanny`)."""
EXIT_NOTE_S = 10.0
"""How long the client waits, once Dask has given up on a point whose worker died, for the nanny's report of how
that worker ended: the two travel apart (the report comes within moments, on a busy machine within seconds)."""
MEMORY_STOP_TOPIC = "worker-restart-memory"
"""The topic of the event a Dask nanny logs as it stops its worker for using more than its memory limit (its memory
manager's, distributed.worker.memory.terminate of the limit: 95% by default), just before it sends SIGTERM (SIGKILL
where that does not end it)."""
CRASH_SIGNALS = ("SIGSEGV", "SIGBUS", "SIGILL", "SIGFPE", "SIGABRT")
"""Signals a process gets from its own fault: it crashed."""
STOP_SIGNALS = ("SIGTERM", "SIGINT", "SIGHUP", "SIGQUIT")
"""Signals that ask a process to stop: it was stopped."""


def emit_event(out: str, point_id: str, event: str, **fields) -> None:
    """Report an event of a point of the sweep in folder `out` (the resolved path the client passed) from a task."""
    worker = get_worker()
    # Dask adds "worker" (the address) to every event; "name" is the worker's own (dask worker --name).
    worker.log_event(EVENT_TOPIC, {"sweep": out, "event": event, "point": point_id, "name": str(worker.name),
                                   "pid": os.getpid(), **fields})


def sweep_name(store: SweepDir) -> str:
    """The folder's one name (resolved), which its tasks are given and its events carry."""
    return str(store.path.resolve())


def dask_point(task: PointTask, out: str, device: str, keep: bool) -> dict:
    """The Dask task of one point: run it on this worker, reporting events to the client; returns a summary."""
    result = run_point(task, out, device=device, keep=keep, worker=str(get_worker().name),
                       emit=lambda event, **fields: emit_event(out, task.id, event, **fields))
    return point_summary(result)


def point_summary(result: dict) -> dict:
    """What the client is told of a finished point: its status and reason, and per method its status, Chamfer
    distance and warnings (how many; a preset that did not converge counts as one where it says nothing of it)."""
    methods = {name: {"status": r.get("status"), "chamfer_mm": r.get("chamfer_mm"), "warnings": warning_count(r)}
               for name, r in (result.get("methods") or {}).items()}
    return {"id": result["id"], "status": result["status"], "reason": result.get("reason"),
            "seconds": result.get("seconds"), "worker": result.get("worker"), "methods": methods,
            "code": result.get("code")}


@dataclass
class Summary:
    """What a run of a sweep did."""

    points: int
    earlier: int
    """Points done before this run (skipped)."""
    ran: int = 0
    done: int = 0
    failed: list[tuple[PointTask, str]] = field(default_factory=list)
    rows: int = 0
    """Rows of results.csv."""
    warned: dict[str, list[str]] = field(default_factory=dict)
    """Points of the sweep (run now or earlier) where a method that gave a result warned: id -> those methods."""
    edge: dict[str, list[str]] = field(default_factory=dict)
    """Points where a baseline's calibrated threshold is at an end of the thresholds tried: id -> those baselines."""
    startup_s: float = 0.0
    """Seconds to start (or reach) the cluster."""
    code: str = ""
    """The client's source hash (fingerprint.code_digest): what a point's result must have been made with to count
    as current here."""
    other_code: dict[str, str] = field(default_factory=dict)
    """Workers that ran a point with other source than the client's: worker -> their source's hash."""


def cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def run_sweep(plan: Plan, out, *, scheduler: str | None = None, workers: int | None = None, device: str = "cpu",
              keep: bool = False, progress: bool = True, log: Callable[[str], None] | None = None,
              point: Callable[..., dict] = dask_point, overwrite: bool = False,
              connect_timeout_s: float | None = None) -> Summary:
    """Run every point of `plan` that DIR `out` does not hold as done; returns the summary. `scheduler`: the
    address of a running Dask scheduler (tcp://host:8786); None starts a LocalCluster of `workers` processes (default:
    one per core; one for CUDA). `point`: the task each point runs, point(task, out, device, keep) -> a summary
    dict with id and status (dask_point; benchmarks/sweep_overhead.py times Dask with one that does nothing).
    `overwrite`: run a plan that drops grid entries DIR holds results of (see SweepDir.open).
    `connect_timeout_s`: how long the scheduler has to answer (default CONNECT_TIMEOUT_S)."""
    log = log or (lambda line: None)
    if device not in DEVICES:
        raise ConfigError(f"device {device!r} is not one of {', '.join(DEVICES)}")
    check_workers(scheduler, workers)
    if scheduler is None:
        device = local_device(device)
    timeout_s = CONNECT_TIMEOUT_S if connect_timeout_s is None else connect_timeout_s
    store = SweepDir(out)
    if scheduler is not None and _points_to_run(plan, store, device)[0]:
        # Before the folder is made or opened: a refused run writes nothing.
        probe_scheduler(scheduler, timeout_s)
    store.open(plan, overwrite=overwrite)
    try:
        todo, stale = _points_to_run(plan, store, device)
        if stale:
            log(stale_line(stale))
        summary = Summary(len(plan.points), len(plan.points) - len(todo), code=code_digest())
        say = None if progress else log
        try:
            if todo:
                _run_on_dask(plan, todo, store, summary, _client(scheduler, workers, device, log, timeout_s),
                             lambda task: (point, task, sweep_name(store), device, keep), device, progress, say)
        except BaseException:
            with contextlib.suppress(OSError):
                # an interrupt or a failure: what finished is gathered all the same
                store.write_results(plan, current_on(plan, device))
            raise
        summary.rows = store.write_results(plan, current_on(plan, device))
        summary.warned, summary.edge = store.endings(plan)
        return summary
    finally:
        store.close()


def _points_to_run(plan: Plan, store: SweepDir, device: str = "cpu") -> tuple[list[PointTask], int]:
    """The points of `plan` that the folder does not hold as done and current on `device` (all of them where there
    is no folder yet), and how many of those it holds done but stale (fingerprint.py)."""
    todo, stale, digests = [], 0, Digests()
    for task in plan.points.values():
        state = Expected(task, device, digests=digests).state(store.read_point(task.id))
        if state != "done":
            todo.append(task)
            stale += state == "stale"
    return todo, stale


def current_on(plan: Plan, device: str) -> Callable[[str, dict], bool]:
    """Whether a point's stored result is current for a run on `device` (not stale: fingerprint.py), for
    results.csv, which leaves a stale one out until it has run again."""
    digests = Digests()
    return lambda point_id, result: Expected(plan.points[point_id], device, digests=digests).state(result) != "stale"


def stale_line(stale: int) -> str:
    """The line that says how many stored points are stale and run again."""
    return (f"{stale} stored point{' is' if stale == 1 else 's are'} stale (run by another spadscan version or "
            f"device, or before a preset's or a baseline's defaults changed): {'it runs' if stale == 1 else 'they run'}"
            f" again; {'its' if stale == 1 else 'each'} old result is kept until the new one is stored, and left out "
            f"of results.csv until then")


def _run_on_dask(plan, todo, store, summary, connect, call, device, progress, say=None) -> None:
    """Submit a task per point of `todo` (`call(task)` gives the function and its arguments) to the client that
    `connect` opens, and record each as it finishes (`say`: where a line per finished point goes, if anywhere)."""
    name = sweep_name(store)
    # Only the embedded cluster's nannies report how their workers ended (ExitNotingNanny).
    exits = WorkerExits() if getattr(connect, "embedded", False) else None

    def on_event(event) -> None:
        _, message = event
        # Other sweeps on the same scheduler publish on the same topic.
        if isinstance(message, dict) and message.get("sweep") == name:
            store.append_log({k: v for k, v in message.items() if k != "sweep"})

    start = time.monotonic()
    with connect as client:
        summary.startup_s = time.monotonic() - start
        topics = [(EVENT_TOPIC, on_event)] + ([(EXIT_TOPIC, exits.note)] if exits is not None else [])
        for topic, handler in topics:
            client.subscribe_topic(topic, handler)
        try:
            _submit_and_gather(plan, todo, store, summary, client, call, device, progress, say, exits)
        finally:
            # Also when interrupted: a scheduler that still counts this client among the topic's subscribers
            # writes the next event to its closed connection, and says so with a traceback.
            for topic, _ in topics:
                with contextlib.suppress(OSError):  # a scheduler already gone has no subscription to end
                    client.unsubscribe_topic(topic)


def _submit_and_gather(plan, todo, store, summary, client, call, device, progress, say=None, exits=None) -> None:
    """Submit a task per point of `todo` and record each as it finishes (`exits`: how the embedded cluster's
    workers ended, WorkerExits)."""
    token = secrets.token_hex(4)  # keys of this run only: another client's tasks never stand in for these
    resources = {"GPU": 1} if device == "cuda" else None
    futures = {}
    for task in todo:
        future = client.submit(*call(task), key=f"spadscan-point-{task.id}-{token}", resources=resources,
                               pure=False)
        futures[future] = task
    with tqdm(total=len(todo), desc="sweep", unit="point", disable=not progress) as bar:
        # Results come with the futures (fetched in the background), not one round trip per point.
        finished = as_completed(futures, with_results=True, raise_errors=False)
        gathered, due = -float("inf"), False  # when results.csv was last gathered; whether it misses a point
        while not finished.is_empty():
            wait_s = max(0.0, gathered + RESULTS_EVERY_S - time.monotonic()) if due else None
            batch = _next_batch(finished, wait_s)
            for future, outcome in batch:
                _record(plan, futures.pop(future), future, outcome, store, summary, device, bar, say, exits)
            due = due or bool(batch)
            # A look at results.csv mid-sweep is current within RESULTS_EVERY_S of a point's end (run_sweep
            # gathers it after the last point).
            if due and time.monotonic() - gathered >= RESULTS_EVERY_S and not finished.is_empty():
                store.write_results(plan, current_on(plan, device))
                gathered, due = time.monotonic(), False


def _next_batch(finished, wait_s: float | None) -> list:
    """The finished (future, outcome) pairs of `finished`: those ready now, else the first to come within `wait_s`
    seconds (None: however long it takes); an empty list when none came in that time or none is left."""
    deadline = None if wait_s is None else time.monotonic() + wait_s
    while not finished.has_ready() and not finished.is_empty():
        if deadline is not None and time.monotonic() >= deadline:
            return []
        time.sleep(POLL_S)
    return finished.next_batch(block=False)


def _record(plan, task, future, outcome, store, summary, device, bar, say=None, exits=None) -> None:
    """Count a finished point in `summary` and on the bar, recording it first when its task raised; with `say`
    (no bar), say a line of it."""
    if future.status == "cancelled" or isinstance(outcome, CancelledError):
        # The client lost its scheduler (Dask cancels every future it held): the point's outcome is not known here,
        # and a worker may still store it; a failure made up for it would replace a stored result.
        raise SpadscanError(f"lost the Dask scheduler with {bar.total - summary.ran} point(s) of this run not "
                            f"finished here ({' '.join(str(outcome).split())[:120]}): nothing is recorded for them, "
                            f"the points finished are kept in {store.path}, and the same command runs the rest")
    # An errored future's outcome is Dask's own record of the error: ask the future for the exception.
    result = _outcome(future.exception() if future.status == "error" else outcome, task, store, device, exits)
    future.release()
    line = other_code_line(result, summary)
    if line is not None:
        (say or (lambda text: bar.write(text, file=sys.stderr)))(line)
    summary.ran += 1
    if result["status"] == "done":
        summary.done += 1
    else:
        summary.failed.append((task, result.get("reason") or "failed"))
    if say is not None:  # a log without a bar (nohup, a batch job) still shows each point as it ends
        say(finished_point_line(plan, task, result, summary.ran, bar.total))
    elif result["status"] != "done":
        # Above the bar, on stderr with it: stdout holds the summary alone.
        bar.write(f"spadscan sweep: failed: {task.describe(plan.spec.base)}: {result.get('reason')}",
                  file=sys.stderr)
    bar.set_postfix(failed=len(summary.failed), refresh=False)
    bar.update(1)


def other_code_line(result: dict, summary: Summary) -> str | None:
    """The line said the first time a worker returns a point made with other source than the client's (another
    install, a local edit): its points are stale to the client, left out of results.csv and run again by every
    sweep, so that the figures always come from the client's code. None otherwise."""
    code, worker = result.get("code"), str((result.get("worker") or {}).get("name") or "a worker")
    if not code or not summary.code or code == summary.code or worker in summary.other_code:
        return None
    summary.other_code[worker] = str(code)
    return (f"spadscan sweep: {worker} runs other spadscan source than this client (source hash {code}, here "
            f"{summary.code}): its points count as stale here, are left out of results.csv and run again by every "
            f"sweep; install the same spadscan on the workers as here")


def finished_point_line(plan, task: PointTask, result: dict, n: int, of: int) -> str:
    """'point 3/12 [id] builtin:sphere views=8: done; fast 5.22 mm, reprojection failed; 2 warnings (fast)' and for a
    failed point its reason at the end. `result`: a point_summary (a task that raised has no methods)."""
    methods = result.get("methods") or {}
    shown = []
    for name in plan.spec.methods:
        r = methods.get(name)
        if r is None:
            continue
        chamfer = r.get("chamfer_mm")
        shown.append(f"{name} {chamfer:.3g} mm" if r.get("status") == "done" and isinstance(chamfer, (int, float))
                     else f"{name} {r.get('status') or 'not run'}")
    warned = {name: r["warnings"] for name, r in methods.items() if r.get("warnings")}
    parts = [f"point {n}/{of} [{task.id}] {task.describe(plan.spec.base)}: {result['status']}"]
    if any(r.get("status") == "done" for r in methods.values()):  # else the reason says it all
        parts.append(", ".join(shown))
    if warned:
        total = sum(warned.values())
        parts.append(f"{total} warning{'' if total == 1 else 's'} ({', '.join(warned)})")
    if result["status"] != "done":
        parts.append(str(result.get("reason") or "failed"))
    return "; ".join(parts)


def _outcome(outcome, task: PointTask, store: SweepDir, device: str, exits: WorkerExits | None = None) -> dict:
    """The summary a finished task returned, or for a task that raised (Dask gave up on it when its workers died, or
    the task could not run at all) a failed point, recorded. `exits`: how the embedded cluster's worker processes
    ended (None on a scheduler's workers, whose endings this client does not learn)."""
    if not isinstance(outcome, BaseException):
        return outcome
    if isinstance(outcome, KilledWorker):
        reason = killed_worker_reason(outcome, exits)
    else:
        reason = f"{type(outcome).__name__}: {' '.join(str(outcome).split())[:300]}"
    expected = Expected(task, device)
    # The methods an earlier attempt stored done and current stay in the point's file, for the next run to keep.
    result = {"id": task.id, "status": "failed", "reason": reason, "scene": task.scene.label,
              "params": task.params, "methods": expected.reusable(store.read_point(task.id)), "device": device,
              "record": task.record, "spadscan": spadscan.__version__, "fingerprints": expected.fingerprints}
    stored = store.write_point(result, expected)
    if stored.get("status") == "done":
        # An attempt whose worker died after storing the point had finished it: report what points/<id>.json says.
        return point_summary(stored)
    store.append_log({"event": "failed", "point": task.id, "reason": reason})
    return result


def killed_worker_reason(error: KilledWorker, exits: WorkerExits | None = None) -> str:
    """Why a point whose workers died failed: how its last worker ended (`process_ending`: a signal's name, or the
    exit code; 'died' where `exits` does not say) and whose log says why; or, where its nanny stopped it for its
    memory (`memory_ending`), which worker it was (its log does not say: the embedded cluster's logs are silenced)."""
    tries = error.allowed_failures + 1
    last = error.last_worker  # Dask's record of the last worker that ran the task (None in a made-up error)
    address = getattr(last, "address", None)
    nanny = getattr(last, "nanny", None)
    code = None if exits is None or not address else exits.wait_for(address, nanny, EXIT_NOTE_S)
    memory = None if code is None else exits.memory_stop(address)
    if memory is not None:
        which = worker_where(last, local=False, address=False)
        which = f" ({which})" if which else ""
        if tries == 1:
            return f"the worker running it{which} {memory_ending(memory)}"
        return (f"the worker running it died each time it was tried ({tries} workers); the last{which} "
                f"{memory_ending(memory)}")
    ending = process_ending(code)
    where = worker_where(last, local=exits is not None)
    if tries == 1:
        return f"the worker running it {ending}; its log says why" + (f" ({where})" if where else "")
    last_one = "" if code is None else f"; the last {ending}"
    return (f"the worker running it died each time it was tried ({tries} workers{last_one}); their logs say why" +
            (f" (the last: {where})" if where else ""))


def process_ending(exitcode: int | None) -> str:
    """How a process ended, from its exit status as multiprocessing gives it (the signal that ended it, negated;
    else its exit code): 'was killed (SIGKILL: ...)', 'crashed (SIGSEGV)', 'was stopped (SIGTERM)', 'exited with
    code 1'; 'died' for None (not known). SIGKILL is what the kernel's out-of-memory killer sends, and what
    `kill -9` does."""
    if exitcode is None:
        return "died"
    if exitcode >= 0:
        return f"exited with code {exitcode}"
    try:
        name = signal.Signals(-exitcode).name
    except ValueError:
        return f"was ended by signal {-exitcode}"
    if name == "SIGKILL":
        return "was killed (SIGKILL: out of memory, or killed by hand?)"
    if name in CRASH_SIGNALS:
        return f"crashed ({name})"
    if name in STOP_SIGNALS:
        return f"was stopped ({name})"
    return f"was ended by {name}"


def memory_ending(memory: dict) -> str:
    """How a worker that its nanny stopped for its memory ended, from the nanny's report (`ExitNotingNanny`: bytes
    it used, its limit and the machine's, the fraction of the limit at which Dask stops a worker): 'was stopped by
    Dask for using too much memory: 480.20 MiB, more than 95% of its 286.10 MiB limit, its share of this machine's
    15.60 GiB (fewer --workers give each more)'; without the share where the worker had the whole machine's."""
    said = (f"was stopped by Dask for using too much memory: {format_bytes(memory['rss'])}, more than "
            f"{memory['terminate']:.0%} of its {format_bytes(memory['limit'])} limit")
    if memory["limit"] < memory["machine"]:
        said += f", its share of this machine's {format_bytes(memory['machine'])} (fewer --workers give each more)"
    return said


def worker_where(worker, local: bool, address: bool = True) -> str:
    """Which worker, so that its log can be found: its name and pid, and where it writes (an embedded cluster's
    workers write to this command's stderr) or (with `address`) its address; '' where Dask did not say."""
    if worker is None:
        return ""
    pid = getattr(worker, "pid", None)
    parts = [f"worker {getattr(worker, 'name', '?')}"] + ([f"pid {pid}"] if pid else [])
    if local:
        parts.append("writing to this command's stderr")
    elif address and getattr(worker, "address", None):
        parts.append(f"at {worker.address}")
    return ", ".join(parts)


def memory_report(memory) -> dict | None:
    """The memory part of a nanny's exit report, checked: {"rss", "limit", "machine": bytes, "terminate": the
    fraction}; None where it is missing or malformed."""
    if not isinstance(memory, dict):
        return None
    sizes = [memory.get(k) for k in ("rss", "limit", "machine")]
    fraction = memory.get("terminate")
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in sizes):
        return None
    if not isinstance(fraction, (int, float)) or isinstance(fraction, bool) or not 0 < fraction <= 1:
        return None
    return {"rss": sizes[0], "limit": sizes[1], "machine": sizes[2], "terminate": float(fraction)}


class WorkerExits:
    """How the embedded cluster's worker processes ended, as their nannies report it (`ExitNotingNanny`): worker
    address -> exit status. The reports come on the client's event thread; `wait_for` is asked on another.

    A worker process that died before its nanny learned its address (at once, as it started) is reported without
    one: its ending is not known, and such a report ends one wait for a worker of its nanny (that wait then says
    "died"), so that points that each kill their worker at once do not each wait EXIT_NOTE_S."""

    def __init__(self):
        self._codes: dict[str, int] = {}
        self._memory: dict[str, dict] = {}
        """Worker address -> what its nanny reported of its memory, where the nanny stopped it for it."""
        self._unnamed: dict[str, int] = {}
        """Nanny address -> its reports without a worker's address that no wait has taken yet."""
        self._reports = 0
        self._timed_out = False
        """A wait ran out before any report had come: until one comes, the nannies are taken not to report (a Dask
        without the hook), and no wait waits."""
        self._changed = threading.Condition()

    def note(self, event) -> None:
        """A subscriber of EXIT_TOPIC: (time, {"worker": address or None, "nanny": address, "exitcode": status,
        and "memory" where the nanny stopped the worker for its memory: see `memory_report`})."""
        _, message = event
        if not isinstance(message, dict):
            return
        address, nanny, code = message.get("worker"), message.get("nanny"), message.get("exitcode")
        if not isinstance(code, int) or isinstance(code, bool):
            return
        with self._changed:
            if isinstance(address, str):
                self._codes[address] = code
                memory = memory_report(message.get("memory"))
                if memory is not None:
                    self._memory[address] = memory
            elif isinstance(nanny, str):
                self._unnamed[nanny] = self._unnamed.get(nanny, 0) + 1
            else:
                return
            self._reports += 1
            self._changed.notify_all()

    def wait_for(self, address: str, nanny: str | None, timeout_s: float) -> int | None:
        """The exit status of the worker at `address` (its nanny at `nanny`), waiting up to `timeout_s` for its
        report; None without one, or once a report of its nanny's without an address has come."""
        def settled() -> bool:
            return address in self._codes or bool(nanny and self._unnamed.get(nanny))

        with self._changed:
            silent = self._timed_out and self._reports == 0
            if not self._changed.wait_for(settled, 0 if silent else timeout_s):
                self._timed_out = True
                return None
            if address in self._codes:
                return self._codes[address]
            self._unnamed[nanny] -= 1
            return None

    def memory_stop(self, address: str) -> dict | None:
        """What the nanny of the worker at `address` reported of its memory where it stopped that worker for using
        more than its limit (`memory_report`); None otherwise (ask once `wait_for` has its exit status)."""
        with self._changed:
            return self._memory.get(address)


class ExitNotingNanny(Nanny):
    """The embedded cluster's nanny: it reports how its worker process ended (the exit status, which only the nanny,
    its parent, learns) as an event on EXIT_TOPIC, so that a point whose worker died can say which signal ended it;
    and where the nanny itself stopped the worker for using more than its memory limit, how much it used.

    Dask has no public hook for a worker process's exit: this extends the nanny's own exit callback, which it passes
    each worker process it starts. A Dask without it never calls this, and the points' reasons then say "died". The
    nanny's memory stop is learnt from the event its memory manager logs through the nanny (MEMORY_STOP_TOPIC); a
    Dask that logs none leaves such a worker's ending at its signal."""

    _reported: str | None = None
    """The worker address of the last exit reported."""
    _memory_stop: dict | None = None
    """The last memory stop's event (the worker's address, its pid and bytes used), until its worker's exit."""

    def log_event(self, topic, msg):
        if topic == MEMORY_STOP_TOPIC and isinstance(msg, dict):
            self._memory_stop = msg
        return super().log_event(topic, msg)

    def _on_worker_exit_sync(self, exitcode):
        address = self.worker_address
        # A process that died as it started, before the nanny read its address, leaves the last one's in place.
        address = None if address == self._reported else address
        self._reported = address or self._reported
        stop, self._memory_stop = self._memory_stop, None
        if self.status == Status.running:  # not the cluster's own close, nor a nanny stopping its worker
            # The report must never keep the nanny from restarting its worker.
            with contextlib.suppress(Exception):
                report = {"worker": address, "nanny": self.address, "exitcode": exitcode}
                memory = self._memory_used(stop, address, exitcode)
                self.log_event(EXIT_TOPIC, report if memory is None else {**report, "memory": memory})
        return super()._on_worker_exit_sync(exitcode)

    def _memory_used(self, stop: dict | None, address: str | None, exitcode) -> dict | None:
        """What this worker's exit report says of its memory: where the nanny stopped this very worker (`stop`, the
        memory stop since the last exit) and the signal is the nanny's (SIGTERM, or SIGKILL where that did not end
        it), the bytes it used, its limit and the machine's, and the fraction of the limit at which Dask stops it."""
        if stop is None or address is None or stop.get("worker") != address:
            return None
        if exitcode not in (-signal.SIGTERM, -signal.SIGKILL):  # it ended otherwise before the signal came
            return None
        manager = self.memory_manager
        return {"rss": stop.get("rss"), "limit": manager.memory_limit, "machine": system.MEMORY_LIMIT,
                "terminate": manager.memory_terminate_fraction}


@contextlib.contextmanager
def _quiet_children():
    """The embedded cluster's start: its processes start with SIGINT blocked, which they inherit (and so do those
    that its threads start later: the threads begin here, and inherit the block too): a terminal's Ctrl-C goes to the
    whole process group, and workers that died of it at once would leave this client's orderly close (the points in
    flight end with the cluster, the points done stay done) a trail of tracebacks. Yet a Ctrl-C or a SIGTERM that
    comes while the cluster starts is neither lost nor let into Dask's start (which then prints tracebacks, and can
    leave processes behind): the block yields the list of those that came, for the caller to act on once the start
    is done. A SIGINT that stays pending (blocked here) is taken at the end; one that a thread of this process that
    does not block it receives (a library's own thread, started earlier) is noted by the handler.

    The processes share one resource tracker, started here: a worker stopped mid-point leaves it the semaphores of
    its point's own processes, which it cleans up at the end, and its warning of "leaked semaphore objects" is
    filtered (that message only, in that process)."""
    caught: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return
    env = os.environ.get("PYTHONWARNINGS")
    os.environ["PYTHONWARNINGS"] = ",".join(filter(None, [env, "ignore:resource_tracker:UserWarning"]))
    before: dict = {}
    blocked = None
    try:
        # Before the block: starting the tracker unblocks SIGINT in the thread that starts it.
        resource_tracker.ensure_running()
        # An ignored Ctrl-C (a script's background job) stays ignored. SIGTERM is noted, not blocked: a blocked
        # SIGTERM, inherited, would keep a nanny from stopping its worker.
        for sig in (signal.SIGINT, signal.SIGTERM):
            if signal.getsignal(sig) is not signal.SIG_IGN:
                before[sig] = signal.signal(sig, lambda signum, frame: caught.append(signum))
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        yield caught
    finally:
        if blocked is not None and signal.SIGINT in signal.sigpending():
            signal.sigwait({signal.SIGINT})  # taken here: unblocked, it would reach the handler restored below
            if signal.SIGINT in before:
                caught.append(signal.SIGINT)
        for sig, handler in before.items():
            signal.signal(sig, handler)
        if blocked is not None and signal.SIGINT not in blocked:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        if env is None:
            os.environ.pop("PYTHONWARNINGS", None)
        else:
            os.environ["PYTHONWARNINGS"] = env


def probe_scheduler(address: str, timeout_s: float) -> None:
    """Refuse, in one line and within about `timeout_s` seconds, an address where no Dask scheduler answers: nothing
    listening, a server that accepts and says nothing (an HTTP server such as the dashboard), one that talks another
    protocol (SSH), a Dask worker. Dask's own connect bounds the connection but not its handshake, and reads
    whatever comes back as Dask's frames (an SSH banner asks it for exabytes): so this asks the address who it is,
    with one deadline for all of it, before the client connects."""
    try:
        reply = asyncio.run(asyncio.wait_for(_identity(address, timeout_s * CONNECT_SHARE), timeout_s))
    except TimeoutError:  # before OSError: TimeoutError is one
        raise ConfigError(f"{address} is not a reachable Dask scheduler: nothing there answered as one within "
                          f"{timeout_s:g} s (a Dask dashboard or another HTTP server? a scheduler listens on "
                          f"port 8786 by default)") from None
    except OSError as exc:
        raise ConfigError(f"{address} is not a reachable Dask scheduler: cannot connect "
                          f"({' '.join(str(exc).split())[:200]})") from None
    except Exception as exc:  # noqa: BLE001 - whatever a foreign protocol makes Dask's reader raise
        raise ConfigError(f"{address} is not a reachable Dask scheduler: what answered there does not speak Dask's "
                          f"protocol ({type(exc).__name__})") from None
    kind = reply.get("type") if isinstance(reply, dict) else None
    if not isinstance(kind, str) or "Scheduler" not in kind:
        what = f"a Dask {kind}" if isinstance(kind, str) else "something else"
        raise ConfigError(f"{address} is not a reachable Dask scheduler: it answers as {what} (give the address "
                          f"the workers were started with: dask worker ADDRESS)")


async def _identity(address: str, connect_s: float):
    """What the Dask server at `address` says it is (its 'identity' reply); the connection is given `connect_s`."""
    comm = await connect(address, timeout=connect_s)
    try:
        await comm.write({"op": "identity", "reply": True})
        return await comm.read()
    finally:
        comm.abort()


@contextlib.contextmanager
def _interrupts_held(hold: bool = True):
    """Within the block, Ctrl-C and SIGTERM wait: the block yields the list of the signals that came meanwhile. The
    cluster's close must end, its worker processes with it, before the points they finished are gathered; a second
    Ctrl-C that broke into the close left those processes to finish their points after results.csv was written.
    With `hold` False, the block runs as is."""
    caught: list[int] = []
    if not hold or threading.current_thread() is not threading.main_thread():
        yield caught
        return
    previous = {sig: signal.signal(sig, lambda signum, frame: caught.append(signum))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield caught
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def worker_memory_limit(workers: int) -> int:
    """Bytes each of an embedded cluster's `workers` processes may use before its nanny stops it: an equal share of
    the machine's memory as Dask measures it (cgroups and ulimit heeded). LocalCluster's default is the same; it is
    given here because a point stopped for its memory says so ("fewer --workers give each more")."""
    return max(1, system.MEMORY_LIMIT // max(1, workers))


class _client:
    """A Dask client on `scheduler`, or on a LocalCluster it starts and stops."""

    def __init__(self, scheduler, workers, device, log, timeout_s: float = CONNECT_TIMEOUT_S):
        self.scheduler, self.workers, self.device, self.log = scheduler, workers, device, log
        self.timeout_s = timeout_s
        self.cluster = self.client = None

    @property
    def embedded(self) -> bool:
        """Whether it starts its own cluster (whose nannies report how their workers end: ExitNotingNanny)."""
        return self.scheduler is None

    def __enter__(self):
        if self.scheduler is not None:
            # run_sweep probed the address before it opened the folder; a scheduler gone since is refused here.
            try:
                self.client = Client(self.scheduler, timeout=self.timeout_s)
            except Exception as exc:  # noqa: BLE001 - a scheduler that went away since the probe, say
                raise ConfigError(f"{self.scheduler} is not a reachable Dask scheduler: "
                                  f"{type(exc).__name__}: {' '.join(str(exc).split())[:200]}") from None
            workers = self.client.scheduler_info().get("workers", {})
            n = len(workers)
            self.log(f"scheduler {self.scheduler}: {n} worker{'' if n == 1 else 's'} connected" +
                     ("" if n else "; points wait until one connects (dask worker " + self.scheduler + ")"))
            if self.device == "cuda" and n and not any(w.get("resources", {}).get("GPU") for w in workers.values()):
                self.log("warning: no connected worker has the resource GPU=1; the points wait for one "
                         "(dask worker ... --resources GPU=1)")
            return self.client
        n = self.workers or (1 if self.device == "cuda" else cores())
        # Loopback only; no dashboard, and the scheduler's HTTP server (health, metrics) on a free port: a fixed
        # 8787 would clash with another cluster on the machine.
        try:
            with _quiet_children() as caught:
                self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                            worker_class=ExitNotingNanny, memory_limit=worker_memory_limit(n),
                                            dashboard_address=None, silence_logs=logging.CRITICAL,
                                            scheduler_kwargs={"dashboard": False,
                                                              "dashboard_address": "127.0.0.1:0"},
                                            **({"resources": {"GPU": 1}} if self.device == "cuda" else {}))
                self.client = Client(self.cluster)
            if caught:
                raise KeyboardInterrupt  # a Ctrl-C or SIGTERM while the cluster started: the sweep ends as one
        except BaseException:
            self.__exit__(*sys.exc_info())  # the cluster's processes are not left running without a client
            raise
        self.log(f"local cluster: {n} worker process{'' if n == 1 else 'es'}, one thread each")
        return self.client

    def __exit__(self, *exc):
        # An embedded scheduler runs in this process: an event a worker sent while the client closed reaches a
        # closed connection, and the scheduler logs that as critical, with a traceback. Nothing is lost by it (every
        # point's outcome is in the sweep's own files), so its close is silent.
        quiet = contextlib.nullcontext() if self.cluster is None else silence_logging_cmgr(logging.CRITICAL + 1)
        # Only the embedded cluster's close is waited for: a scheduler's workers go on with their points regardless.
        with quiet, _interrupts_held(self.cluster is not None) as caught:
            if self.client is not None:
                self.client.close()
            if self.cluster is not None:
                self.cluster.close()
        if caught and exc[0] is None:
            raise KeyboardInterrupt  # a Ctrl-C during the close of a sweep that had ended: the sweep ends as one
        return False


__all__ = ["run_sweep", "probe_scheduler",
           "dask_point", "point_summary", "finished_point_line", "other_code_line", "emit_event", "Summary",
           "killed_worker_reason", "process_ending", "memory_ending", "WorkerExits", "ExitNotingNanny",
           "worker_memory_limit", "EVENT_TOPIC", "EXIT_TOPIC", "MEMORY_STOP_TOPIC", "cores"]
