"""The worker: watches a captures root, claims jobs from the durable queue and runs each in a child process.

One asyncio loop does everything the worker process itself does: the watcher queues complete scans, the loop claims
jobs while it has free slots, renews the leases of the jobs it holds, takes over jobs whose holders died, and settles
each job when its child exits. A job runs in `python -m spadscan.worker.jobs` (its own process: torch, memory and
crashes stay there) with its output in a log file under the queue. Stopping (Ctrl-C, SIGTERM, `stop` set) ends the
children and gives their jobs back to the queue without counting the attempt; a live job's status then says it is
queued again (`mark_live_queued`), as it does when a crashed live job is retried, when a dead worker's job is taken
over and queued again, and whenever a job is given back with a finished result that could not be published.

A finished job whose result cannot be published (a full disk while its log is copied in or its marker written) keeps
its claim and its scratch folder: the worker says so once and tries again at every poll, as it does with every other
write that meets a full disk; its other jobs run on. A result already renamed into place whose job's record cannot
be written yet is published, not lost: the worker writes the record once it fits. A finished result a stopped worker
left unpublished is published by the worker that claims its job next (publishing.left_result), not reconstructed
again. A job that ended in error whose record a full disk keeps out is said where it went and why, its record written
at a later poll. A job whose own process met a full disk is not at fault, and a retry would meet the same disk: it
goes back to the queue without counting an attempt, its line naming the folder that is full and where to make room,
and the worker claims no job until there is room (`disk_room.RoomWait`), saying so once and again when it goes on.
The job's attempt record carries that wait, so that no worker claims a job while its room is still missing
(`Queue.claim`): a worker that finds such a wait in the queue waits too, and says so, and goes on as soon as the queue
holds that wait no more (the job claimed, settled or removed). A worker's presence file says the wait it is in
(`room_wait`). A job that finished, whose outcome file alone met a full disk (the queue's), is
published, not reconstructed again (`jobs.EXIT_DONE_UNSAID`).
"""

from __future__ import annotations

import asyncio
import json
import math
import shutil
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from spadscan.protocol.capture_format import fold
from spadscan.protocol.errors import ConfigError

from .children import Child, exit_reason, kill_group, spawn_job
from .disk_room import MAX_FULL_DISK, RoomWait, folder_bytes, mount_point, retry_after, same_filesystem
from .job_progress import PROGRESS_S, LogTails, ProgressNotes, claim_budget, ended_live_status, progress_note
from .jobs import (CHANGEABLE, EXIT_DONE_UNSAID, EXIT_FULL, EXIT_INPUT, completion, existing_result, mark_complete,
                   redo_command, result_path, scan_state, scratch_path, summary_of, worker_command)
from .holder import Holder
from .overdue import overdue_reason
from .live.done import SCAN_ABORTED, mark_live_done, mark_live_failed, mark_live_queued
from .presence import RENEW_S, Presence, machine_siblings, remove_presence, write_presence
from .publishing import left_result, own_result, publish_claim, publish_left, reconcile
from .queue import QUEUE_DIRNAME, SEP, Claim, Queue, Unrecorded
from .watcher import SETTLE_S, ScanReport, scan_once, watch
from .worker_config import WorkerConfig, machine_job_processes


@dataclass
class Unpublished:
    """A job whose process finished with a result that could not be published yet: its claim is still held (and
    renewed) and its scratch folder kept until `Worker._publish` succeeds."""

    child: Child
    seconds: float
    """How long the job had run when its process ended (the done line's time)."""
    summary: dict
    """The job's outcome summary (the done line's Chamfer and warnings)."""


class Worker:
    """Runs jobs from the queue in child processes. `log` receives one message per event, each one line but a done
    line, which carries its report's warnings on indented lines of its own. `progress_s`: say each running job's
    progress every so many seconds and when its stage changes (`ProgressNotes`; None: never, `run_worker`: 30 s)."""

    def __init__(self, config: WorkerConfig, log: Callable[[str], None] | None = None,
                 progress_s: float | None = None):
        self.config = config.check()
        self.root = Path(config.root)
        self.queue = Queue(config.queue_dir or self.root / QUEUE_DIRNAME, lease_s=config.lease_s,
                           max_attempts=config.max_attempts, root=self.root)
        (self.queue.path / "logs").mkdir(exist_ok=True)
        self.log = log or (lambda line: print(f"spadscan worker: {line}", file=sys.stderr, flush=True))
        self.children: dict[str, Child] = {}
        self.unpublished: dict[str, Unpublished] = {}
        """Finished jobs whose results wait to be published (a full disk): tried again at every poll."""
        self.unrecorded: dict[str, tuple[Claim, dict]] = {}
        """Jobs that ended in error, settled in the queue, whose attempt records (with the error) a full disk kept
        out: job id -> (claim, what the record must say). Written at a later poll."""
        self.settled: dict[str, str] = {}
        """Job id -> 'done' or 'failed' for jobs this worker finished, 'kept' for jobs it did not run because their
        results folder already held a result."""
        self.left: dict[str, str] = {}
        """With `once`: scans the run looked at and left unqueued (still recorded, or a copy still under way) -> why,
        in a few words (`_left_why`)."""
        self.untakeable: dict[str, str] = {}
        """Queued jobs this worker may not take (another user's on a shared queue: `Queue.claim`'s `skipped`) -> the
        error, in one line: left for a worker that may, and not waited for by a --once run (`_drained`)."""
        self._seen_skipped: set[str] = set()
        self._troubles: dict[str, str] = {}
        """What this worker failed to do, with the error last logged for it (`_trouble`)."""
        self._reconciled = False
        """Whether the queue and the result folders were reconciled at start-up (publishing.reconcile)."""
        self._frozen_named: set[str] = set()
        """Jobs already named as keeping options other than this worker's (`_say_frozen_options`): named once."""
        self._reconcile_due = True
        self.job_env = config.job_env()
        """Environment the job processes get on top of the worker's own (threads per job, child_env): the cores
        shared out among this worker's job processes and the other workers' on its machine (`_share_cores`)."""
        self.threads_note = config.threads_note()
        self.threads_warnings = config.threads_warnings()
        self.siblings: list[dict] = []
        """The other workers on this machine (`presence.machine_siblings`) when a job last started (or at start-up):
        their job processes count in the cores shared out."""
        self._siblings_key: tuple | None = None
        """Who `siblings` are, as `_share_cores` compares them: None before the first look."""
        self.progress = ProgressNotes(progress_s) if progress_s else None
        self.tails = LogTails()
        """The running jobs' logs as last read for their progress lines: read again only once changed."""
        self.room: RoomWait | None = None
        """While set, a job met a full disk: no job is claimed until there is room (`_room_again`)."""
        self._adopted: str | None = None
        """The queued job whose wait `room` is, where it is another's (`_adopt_wait`): followed in the queue."""
        self._doubts_said: set[tuple[str, str]] = set()
        """(job id, why) of the queued waits said to be read otherwise than they say (`_say_doubts`): said once."""
        self._full_in_row = 0
        """Jobs that met a full disk since one last finished (`disk_room.retry_after`)."""
        self.presence = Presence(Holder.current().to_dict(), str(self.root.resolve()), time.time(), config.processes,
                                 config.once)
        """What this worker says of itself in its file under the queue (presence.py), renewed while it runs."""
        self._presence_at = -math.inf

    # ---- main loop -------------------------------------------------------------------------------------------
    async def run(self, stop: asyncio.Event | None = None) -> dict[str, str]:
        """Work until `stop` is set (or, with `once`, until the queue is drained). Returns `settled`."""
        stop = stop or asyncio.Event()
        # killed workers' files tidied away; the other workers on this machine share the cores with this one's jobs
        self._share_cores(await asyncio.to_thread(machine_siblings, self.queue.path, self.presence.holder, tidy=True))
        self.log(f"watching {self.root} with {self.config.processes} job process(es) at once, "
                 f"{self.threads_note}")
        if self.siblings:  # the line above says the threads per job: this one names the workers
            self.log(self._siblings_line(threads_said=True))
        for warning in self.threads_warnings:
            self.log(f"warning: {warning}")
        self._say_present()  # before the start-up work, which may take a while on a large root
        await asyncio.to_thread(self._say_frozen_options)  # before this worker queues jobs of its own
        watcher = None
        if self.config.once:
            self._on_scan(await asyncio.to_thread(scan_once, self.root, self.queue, self.config.options))
        else:
            watcher = asyncio.create_task(watch(self.root, self.queue, self.config.options, stop,
                                                poll_s=self.config.poll_s, on_report=self._on_scan,
                                                on_error=lambda exc: self._trouble("look for scans", exc)))
        next_poll = 0.0
        try:
            while not stop.is_set():
                if watcher is not None and watcher.done():
                    break  # it ended on an error it could not survive: raised below, after the jobs are stopped
                if time.monotonic() >= next_poll:
                    if self.unpublished:
                        await asyncio.to_thread(self._publish_waiting)
                    if self.unrecorded:
                        await asyncio.to_thread(self._record_waiting)
                    try:
                        await self._poll_queue()
                        self._trouble("poll the queue", None)
                    except OSError as exc:  # a full disk, a queue on a lost mount: try again at the next poll
                        self._trouble("poll the queue", exc)
                    next_poll = time.monotonic() + self.config.poll_s
                self._heartbeat()
                self._say_present()
                await self._say_progress()
                await self._stop_overdue()
                if self.config.once and not self.children and not self.unpublished and self._drained():
                    break
                # renewals due too: a poll longer than the presence's window would hide an idle worker
                await self._wait(stop, min(self.config.poll_s, self.config.lease_s / 4, RENEW_S))
                await self._reap()
        finally:
            stop.set()
            try:
                if watcher is not None:
                    await watcher
            finally:
                await self._shutdown()
                self._say_gone()
        return self.settled

    def _trouble(self, what: str, exc: Exception | None) -> None:
        """Log a failed attempt to `what` once, not at every poll while it keeps failing the same way, and log when it
        works again (exc None: it worked)."""
        line = None if exc is None else fold(exc)
        if line == self._troubles.get(what):
            return
        if line is None:
            self.log(f"could {what} again")
            self._troubles.pop(what)
        else:
            self.log(f"could not {what}: {line}; trying again every {self.config.poll_s:g} s")
            self._troubles[what] = line

    def _say_present(self) -> None:
        """Renew this worker's presence file every RENEW_S, and at once when the jobs it runs change: the dashboard
        and `--status` tell an idle worker from none by it. A write that fails (a full disk) is said once; the worker
        works on without it."""
        running = sorted(self.children)
        wait = None if self.room is None else self.room.note()
        same = running == self.presence.running and _wait_key(wait) == _wait_key(self.presence.room_wait)
        if same and time.monotonic() - self._presence_at < RENEW_S:
            return  # a wait that begins or ends is said at once, its free space at the next renewal
        self.presence.running = running
        self.presence.room_wait = wait
        self._presence_at = time.monotonic()
        try:
            write_presence(self.queue.path, self.presence)
            self._trouble("renew this worker's presence file", None)
        except OSError as exc:
            self._trouble("renew this worker's presence file", exc)

    def _say_gone(self) -> None:
        try:
            remove_presence(self.queue.path, self.presence)
        except OSError as exc:  # a lost mount: the file counts no more once it is a few renewals old
            self.log(f"could not remove this worker's presence file: {fold(exc)}")

    def _drained(self) -> bool:
        """Nothing queued or running, the queued jobs this worker may not take aside: a --once run waited on them
        for good."""
        return not self.queue.queued_ids() - self.untakeable.keys() and self.queue.counts()["running"] == 0

    async def _wait(self, stop: asyncio.Event, timeout: float) -> None:
        """Sleep until a child exits, `stop` is set or `timeout` passes."""
        stopper = asyncio.ensure_future(stop.wait())
        waits = [c.wait for c in self.children.values()]
        await asyncio.wait([stopper, *waits], timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
        if not stopper.done():
            stopper.cancel()
            await asyncio.gather(stopper, return_exceptions=True)

    async def _poll_queue(self) -> None:
        """Reconcile the queue with the result folders (at start-up, and after dead workers' jobs were taken over),
        take over jobs of dead workers, finish cut-short enqueues, claim jobs for the free slots."""
        if self._reconcile_due:
            await asyncio.to_thread(self._reconcile)
        await self._take_over()
        await asyncio.to_thread(self.queue.repair)
        if self.room is None or self._adopted is not None:  # another's job (or an earlier run's) may wait for room
            doubts: list[tuple[str, str]] = []
            waiting = await asyncio.to_thread(self.queue.room_wait, None, doubts)
            self._say_doubts(doubts)
            await asyncio.to_thread(self._follow_queue_wait, waiting)
        if self.room is not None and not await asyncio.to_thread(self._room_again):
            return  # a claim now would meet the full disk again
        while len(self.children) + len(self.unpublished) < self.config.processes:  # a result to publish holds its slot
            skipped: list[tuple[str, OSError]] = []
            claim = await asyncio.to_thread(self.queue.claim, None, skipped)
            for job_id, exc in skipped:  # said once a job: it stays queued for a worker that may take it
                self._trouble(f"claim job {job_id}", exc)
                self.untakeable[job_id] = fold(exc)
            if claim is None:
                break
            await self._start(claim)

    async def _take_over(self) -> None:
        """Take over the jobs of dead workers (`Queue.take_over_expired`): each is queued again, a live job's status
        saying so while this worker holds it (`_say_reclaimed`), or failed on its last attempt (`_gave_up`)."""
        reclaimed = await asyncio.to_thread(self.queue.take_over_expired, before_requeue=self._say_reclaimed)
        for taken in reclaimed:  # its worker died (its process is gone) or went silent: said as --status says it
            self.log(f"{taken.job_id}: {taken.why}; {'queued again' if taken.state == 'queued' else 'failed'}")
        if reclaimed:
            await asyncio.to_thread(self._reconcile)
        for taken in reclaimed:
            if taken.state == "failed":  # this worker gave up on it: counted as failed here (--once's exit status)
                await asyncio.to_thread(self._gave_up, taken.job_id)

    def _say_reclaimed(self, job, why: str) -> None:
        """A live job whose worker died goes back to the queue: its status says so (`mark_live_queued`), as on every
        other path that gives a job back, instead of going on saying that it follows its scan or finishes with no
        process running it. Called while this worker holds the job (`Queue.reclaim_expired`)."""
        mark_live_queued(job, self.root, why, self.log)

    def _reconcile(self) -> None:
        """publishing.reconcile: publish the finished results dead workers left, remove their partial ones, settle
        jobs whose results are in place, and (at start-up) queue again done jobs whose results are gone.

        Folders are listed before their claims are looked at: a claim's record is written before its scratch
        folder is made, so a folder in use always has a record that names a live holder."""
        busy = {c.claim.token for c in self.children.values()}
        self._reconcile_due = reconcile(self.queue, self.root, self.log, busy=busy, startup=not self._reconciled)
        self._reconciled = True
        # A done job whose result is gone, a dead worker's job taken over: queued again with their own options.
        self._say_frozen_options()

    def _say_frozen_options(self) -> None:
        """Log `_frozen_options_note` for the queued jobs it has not named yet: at start-up, and after each reconcile,
        which may have queued jobs again (a done job whose result is gone, a dead worker's job taken over)."""
        differ = self._frozen_options([job for job in self.queue.queued_jobs() if job.id not in self._frozen_named])
        self._frozen_named.update(differ)
        note = self._frozen_options_note(differ)
        if note:
            self.log(note)

    def _frozen_options(self, jobs) -> dict[str, str]:
        """Job id -> its own values of the options this worker was given, for those of `jobs` whose values differ."""
        differ = {}
        for job in jobs:
            own = [f"{k} {_shown(getattr(job, k))}" for k, value in self._options_given().items()
                   if getattr(job, k) != value]
            if own:
                differ[job.id] = ", ".join(own)
        return differ

    def _options_given(self) -> dict[str, object]:
        """The job options this worker was given (all of jobs.CHANGEABLE where the config does not say) -> values."""
        given = self.config.options_given
        return {k: getattr(self.config.options, k) for k in CHANGEABLE if given is None or k in given}

    def _frozen_options_note(self, differ: dict[str, str], most: int = 10) -> str | None:
        """A line naming the queued jobs `differ` (id -> their own values) that will run with options other than the
        ones this worker was given (a job keeps the options it was queued with), or None."""
        if not differ:
            return None
        named = [f"{job_id} ({own})" for job_id, own in differ.items()]
        more = f" and {len(named) - most} more" if len(named) > most else ""
        asked = ", ".join(f"{k} {_shown(v)}" for k, v in self._options_given().items())
        return (f"{len(named)} job(s) queued earlier keep the options they were queued with, not {asked}: "
                f"{', '.join(named[:most])}{more}")

    def _on_scan(self, report: ScanReport) -> None:
        self._trouble("look for scans", None)
        for name in report.queued:
            self.log(f"queued scan {name}")
        for name in report.live:
            self.log(f"queued scan {name} as a live job (it is still being recorded)")
        for name in report.unreadable:
            self.log(f"queued scan {name} (its manifest is unreadable: the job will say why)")
        if self.config.once:  # looked at once only: say what this run leaves (a watching worker looks again)
            for name in report.pending:
                self.log(_not_queued(name, report.settling.get(name)))
                self.left[name] = _left_why(report.settling.get(name))
        for name in report.skipped:
            if name not in self._seen_skipped:
                self._seen_skipped.add(name)
                self.log(f"skipping aborted scan {name}")

    # ---- one job ---------------------------------------------------------------------------------------------
    async def _start(self, claim: Claim) -> None:
        job = claim.job
        existing = await asyncio.to_thread(existing_result, job, self.root)
        if existing is not None:
            await asyncio.to_thread(self._keep, claim, existing)
            return
        left = await asyncio.to_thread(left_result, self.queue, claim, self.root)
        if left is not None:
            await asyncio.to_thread(self._publish_left, claim, left)
            return
        stem = f"{job.id}{SEP}{claim.token}"
        log_path = self.queue.path / "logs" / f"{stem}.log"
        outcome = self.queue.path / "tmp" / f"outcome-{stem}.json"
        try:
            scratch = scratch_path(job, self.root, claim.token)
            if not scratch.parent.parent.is_dir():  # made with its parents, the folder of a removed scan came back
                raise ConfigError(f"its capture folder {scratch.parent.parent} is gone (moved or removed)")
            scratch.parent.mkdir(exist_ok=True)
        except (ConfigError, OSError) as exc:
            self.queue.fail(claim, f"cannot prepare the result folder: {exc}", retry=False)
            self.settled[job.id] = "failed"
            self.log(f"{job.id} failed: cannot prepare the result folder: {exc}")
            return
        await self._share_cores_now()
        # the job's log names the workers it shares the cores with: a busy warning in its report may come from them
        proc = await spawn_job(job, self.root, scratch, outcome, log_path, recon=self.config.recon,
                               extra_env=self.job_env, preface=[self._siblings_line()] if self.siblings else None,
                               queue=self.queue.path)
        self.children[job.id] = Child(claim, proc, scratch, outcome, log_path, asyncio.create_task(proc.wait()))
        await asyncio.to_thread(self.queue.note_job_process, claim, proc.pid)
        self.log(f"{job.id} started (attempt {claim.attempt} of {self.queue.max_attempts}, pid {proc.pid})")

    async def _share_cores_now(self) -> None:
        """Look again at the other workers on this machine before a job starts (its threads are fixed for its whole
        run) and share the cores with them; say so when they changed since the last look, not at every poll."""
        before = self.threads_warnings
        if self._share_cores(await asyncio.to_thread(machine_siblings, self.queue.path, self.presence.holder)):
            self.log(self._siblings_line())
            for warning in self.threads_warnings:
                if warning not in before:
                    self.log(f"warning: {warning}")

    def _share_cores(self, siblings: list[dict]) -> bool:
        """Give the jobs started from now on the cores shared out among this worker's job processes and those of
        `siblings`, the other workers on this machine (`presence.machine_siblings`). Returns whether they changed
        since the last look (always False at the first: the start-up lines say it)."""
        key = tuple(sorted((r["host"], r["pid"], machine_job_processes([r])) for r in siblings))
        changed, first = key != self._siblings_key, self._siblings_key is None
        self._siblings_key, self.siblings = key, siblings
        others = machine_job_processes(siblings)
        self.job_env = self.config.job_env(others=others)
        self.threads_note = self.config.threads_note(others=others)
        self.threads_warnings = self.config.threads_warnings(others=others)
        return changed and not first

    def _siblings_line(self, threads_said: bool = False) -> str:
        return self.config.siblings_line(self.siblings, host=self.presence.holder["host"], threads_said=threads_said)

    def _keep(self, claim: Claim, existing: Path) -> None:
        """Record a job whose results folder already holds a result as done, without running it: a result is never
        replaced in silence (it may come from another queue, or from before the queue was deleted). A result that
        an earlier claim of this job in this queue published (its worker died before it recorded the job as done)
        is the job's own: the job is done, not 'kept'."""
        if own_result(self.queue, claim.job.id, existing) is not None:
            if self.queue.finish(claim, str(existing)):
                self.settled[claim.job.id] = "done"
                self.log(f"{claim.job.id}: its result {existing} was published by an earlier attempt whose worker "
                         "died before recording it; recorded the job as done")
                if claim.job.live:  # that worker died before its live status could say so
                    mark_live_done(claim.job, self.root, existing, self.log)
            return
        if not self.queue.finish(claim, str(existing), kept=True):
            return
        self.settled[claim.job.id] = "kept"
        self.log(f"{claim.job.id}: not run, {existing} already holds a result; kept it and recorded the job as done "
                 f"(`{redo_command(claim.job, self.root, self.queue.path)}` moves this one aside and queues the job "
                 f"again; a worker on this queue then reconstructs it)")

    def _publish_left(self, claim: Claim, left: Path) -> None:
        """Publish the finished result an earlier claim of this job left in `left` (its worker stopped, or died,
        before it could publish it) instead of reconstructing the job again. A write that fails (the disk still
        full) gives the job back, the folder whole: the next claim of it tries again."""
        job = claim.job
        what = f"publish the finished result of {job.id} left in {left}"
        try:
            final, aside = publish_left(self.queue, claim, left, self.root)
        except OSError as exc:
            self._trouble(what, exc)
            self._give_back(claim, f"could not publish the result left in {left}: {exc}")
            return
        self._trouble(what, None)
        if job.live:
            mark_live_done(job, self.root, final, self.log)
        self.settled[job.id] = "done"
        self.log(f"{job.id}: published the finished result an earlier attempt left in {left.name} (not reconstructed "
                 f"again) -> {final}" + (f" (moved {aside} aside)" if aside else ""))

    def _heartbeat(self) -> None:
        now = time.monotonic()
        for job_id, child in list(self.children.items()):
            if now - child.last_beat < self.config.lease_s / 4:
                continue
            child.last_beat = now
            if not self.queue.heartbeat(child.claim):
                removed = self._removed(child)
                self.log(f"{job_id}: {removed}; stopping its process" if removed else
                         f"{job_id}: lease lost to another worker; stopping its process and dropping the result")
                kill_group(child.proc, signal.SIGKILL)
        for job_id, waiting in list(self.unpublished.items()):
            child = waiting.child
            if now - child.last_beat < self.config.lease_s / 4:
                continue
            child.last_beat = now
            if not self.queue.heartbeat(child.claim) and not self._done_in_place(child):
                self._drop_unpublished(job_id, self._removed(child) or "its lease was taken over by another worker")

    async def _say_progress(self) -> None:
        """Log the progress lines that are due (`ProgressNotes`): without them the worker's own terminal says nothing
        between a job's start and its end, minutes or hours later."""
        if self.progress is None:
            return
        running = list(self.children.values())
        for line in await asyncio.to_thread(self._progress_lines, running):
            self.log(line)

    def _progress_lines(self, running: list[Child]) -> list[str]:
        self.progress.keep_only(child.claim.token for child in running)
        self.tails.keep_only(child.log for child in running)
        lines = []
        for child in running:
            note = progress_note(child.claim, child.log, self.root, tails=self.tails)
            if self.progress.due(child.claim.token, note):
                lines.append(note.text)
        return lines

    async def _stop_overdue(self) -> None:
        """Stop the job processes that have run far past their budget (`overdue.py`), as a shutdown stops them
        (SIGTERM, then SIGKILL after the grace period); `_reap` then records each as a crash that says why."""
        for job_id, child in list(self.children.items()):
            if child.wait.done():
                continue
            if child.stopped_why is not None:
                if time.monotonic() >= child.kill_at:
                    kill_group(child.proc, signal.SIGKILL)
                continue
            job = child.claim.job
            if job.live:  # its budget counts from its scan's end, which its live status tells on the wall clock
                why = overdue_reason(await asyncio.to_thread(claim_budget, job, child.claim.started, self.root),
                                     time.time())
            else:  # from its process's start, on a clock that a suspended machine does not move on
                budget = claim_budget(job, child.spawned, self.root)
                why = overdue_reason(budget, time.monotonic())
            if why is not None:
                child.stopped_why, child.kill_at = why, time.monotonic() + self.config.stop_grace_s
                kill_group(child.proc, signal.SIGTERM)
                self.log(f"{job_id}: {why}; stopping it")

    async def _reap(self) -> None:
        for job_id, child in list(self.children.items()):
            if child.wait.done():
                del self.children[job_id]
                await asyncio.to_thread(self._settle, child)

    def _settle(self, child: Child) -> None:
        claim, job = child.claim, child.claim.job
        rc = child.proc.returncode
        try:
            outcome = json.loads(child.outcome.read_text())
        except (OSError, ValueError):
            outcome = {}
        child.outcome.unlink(missing_ok=True)
        seconds = time.time() - claim.started
        try:
            if rc == 0 and outcome.get("ok"):
                self._settle_done(child, seconds, outcome.get("summary") or {})
            elif rc == EXIT_DONE_UNSAID:
                self.log(f"{job.id}: finished, but its outcome file did not fit in {child.outcome.parent} (no room "
                         f"left on the disk): publishing its result all the same, not reconstructing it again")
                self._settle_done(child, seconds, _report_summary(child.scratch))
            elif rc == EXIT_FULL:
                self._settle_full(child, outcome, seconds)
            else:
                self._settle_error(child, rc, outcome, seconds)
        finally:
            # A complete result is never removed, nor one still to be published (`unpublished`).
            if job.id not in self.unpublished and child.scratch.exists() and completion(child.scratch) is None:
                shutil.rmtree(child.scratch, ignore_errors=True)

    def _settle_error(self, child: Child, rc: int | None, outcome: dict, seconds: float) -> None:
        """Record a job that failed (bad input), crashed, or ended as its aborted scan did (a live job, or any job
        that failed on a scan whose manifest says aborted: failed in the queue, with nothing to retry,
        `SCAN_ABORTED`). A record the queue cannot write (a full disk) does not end the worker and its other jobs:
        the line says where the job is and why it ended, and the record is written at a later poll (`unrecorded`); a
        job file that could not even be moved stays held until its lease runs out."""
        claim, job = child.claim, child.claim.job
        bad_input = outcome.get("kind") == "input"
        # its own word, written by this attempt: an earlier attempt's 'aborted' says nothing of this one's failure
        ended = ended_live_status(self.root, job, claim.started) if bad_input and job.live else None
        # Or its scan's manifest says aborted (an ordinary job, a second live job run as one: `Queue.live_claim`).
        by_scan = bad_input and scan_state(job, self.root) == "aborted"
        aborted = (ended is not None and ended.state == "aborted") or by_scan
        if aborted:  # no fault: the job ended as its scan did, and a retry would follow a scan that has ended
            error = f"{SCAN_ABORTED} ({outcome.get('error', 'its scan was aborted')})"
            said = f"{job.id} ended after {seconds:.1f} s: {error}"
        elif bad_input:
            error = outcome.get("error", "bad input")
            said = f"{job.id} failed after {seconds:.1f} s: {error}"
        else:
            reason = child.stopped_why or outcome.get("error") or exit_reason(rc)
            error = f"{reason} (log: {child.log})"
            said = f"{job.id} crashed after {seconds:.1f} s: {reason}"
        if not bad_input and claim.attempt < self.queue.max_attempts:  # queue.crash retries it: queued again
            self._say_queued(claim, f"its process crashed ({fold(error)})")
        try:
            state = self.queue.fail(claim, error, retry=False) if bad_input else self.queue.crash(claim, error)
        except Unrecorded as exc:
            state = exc.state
            self.unrecorded[job.id] = (claim, exc.values)
            self._troubles[_recording(job.id)] = fold(exc)  # said here: not again at the next poll
            note = (f"; {_moved_to(state, bad_input)}, but its attempt record could not be written "
                    f"({fold(exc)}): trying again every {self.config.poll_s:g} s")
        except OSError as exc:  # the job file was not moved: the job stays held by this worker's claim
            self.log(f"{said}; the queue could not record it ({fold(exc)}): the job stays in "
                     f"running/ until its lease runs out in {self.config.lease_s:g} s, then it is taken again")
            return
        else:
            if state is None:
                return  # the lease had been lost: the job is another worker's now
            note = "" if bad_input else f"; {_moved_to(state, bad_input)}"
        if state == "failed":
            self._settle_failed(job, error)
            if not (self.root / job.scan).is_dir():  # moved out or deleted: a retry would fail as well
                note += f" (its scan {job.scan} is gone from {self.root}: nothing to try again)"
            elif not aborted:
                note += (f" (once the cause is fixed, `{worker_command(self.root, self.queue.path, '--retry-failed')}` "
                         "queues it again)")
        self.log(said + note)

    def _settle_full(self, child: Child, outcome: dict, seconds: float) -> None:
        """A job whose process met a full disk: its partial result is removed (room for its record, and a fair
        measure of what is free), the job given back without counting an attempt, its record carrying the wait for
        room it begins, and no job claimed until there is room (`RoomWait`). One line names the folder that is full
        and what to do; the wait is said once."""
        claim, job = child.claim, child.claim.job
        folder = _full_folder(child, outcome)
        quota = outcome.get("quota") is True
        # what the partial result took counts only on its own filesystem (the queue's may be another)
        held = folder_bytes(child.scratch) if same_filesystem(child.scratch, folder) else 0
        shutil.rmtree(child.scratch, ignore_errors=True)
        room_of = "in the disk quota" if quota else "on the disk"
        why = f"no room left {room_of}: {folder} could not be written ({outcome.get('error') or 'disk full'})"
        in_quota = "in this user's disk quota " if quota else ""
        remedy = f"make room {in_quota}on the filesystem mounted at {mount_point(folder)}"
        times = 1 + sum(1 for r in self.queue.records(job.id) if r.get("outcome") == "disk_full")
        if times >= MAX_FULL_DISK:  # it may never fit: failed, counted (a --once run ends then too)
            given_up = f"it met a full disk {times} times: its result may need more room than the disk frees"
            self._settle_error(child, EXIT_INPUT, {"kind": "input", "error": f"{why}; {remedy} ({given_up})"},
                               seconds)
            return
        wait = self._job_wait(folder, held, quota, job.id)
        self._say_queued(claim, why)
        uncounted = "not counted as an attempt"
        try:
            given = self.queue.release(claim, f"{why}; {remedy}, then a worker runs the job again", outcome="disk_full",
                                       room=wait.note())
        except Unrecorded as exc:
            given = True
            self.unrecorded[job.id] = (claim, exc.values)
            self._troubles[_recording(job.id)] = fold(exc)  # said here: not again at the next poll
            # until its record says disk_full, the claim's 'running' record counts: said as it is
            uncounted = (f"but its attempt record could not be written ({fold(exc)}): trying again every "
                         f"{self.config.poll_s:g} s, then it is not counted as an attempt")
        except OSError as exc:  # the job file was not moved: held until its lease runs out
            self.log(f"{job.id} stopped after {seconds:.1f} s: {why}; the queue could not take it back "
                     f"({fold(exc)}): {remedy}; it is taken again once its lease runs out")
            given = False
        if given:
            self.log(f"{job.id} stopped after {seconds:.1f} s: {why}; back in the queue, {uncounted}; "
                     f"{remedy}, then this worker runs it again by itself")
        self._begin_wait(wait)

    def _job_wait(self, folder: Path, held: int, quota: bool, job_id: str | None) -> RoomWait:
        """The wait for room of a job that met a full disk writing into `folder` (its record carries it): this
        worker's own wait where it waits on that filesystem already (the jobs that meet the full disk with it
        lengthen no wait), else a new one (`RoomWait.begin`; on its timer alone where the free space cannot be
        asked: a lost mount)."""
        room = self.room
        if room is not None and room.mount == mount_point(folder) and room.quota == quota:
            return room
        retry_s = retry_after(self._full_in_row + (room is None))
        try:
            return RoomWait.begin(folder, held, retry_s, quota=quota, job=job_id, roots=self.queue.roots)
        except OSError as exc:
            self.log(f"could not check the free space on the disk of {folder} ({fold(exc)}): claiming again in "
                     f"{retry_s / 60:.0f} min")
            return RoomWait.unasked(folder, retry_s, quota=quota, job=job_id, roots=self.queue.roots)

    def _begin_wait(self, wait: RoomWait) -> None:
        """Make `wait` this worker's own, said once, unless it waits already (one wait at a time)."""
        if self.room is not None:
            return
        self._full_in_row += 1
        self.room = wait
        if wait.quota or wait.need is not None:  # one whose free space cannot be asked was said by `_job_wait`
            self.log(wait.begun_line(self.config.poll_s))

    def _follow_queue_wait(self, waiting: tuple[str, dict] | None) -> None:
        """Follow the queue's wait for room (`Queue.room_wait`: None, or the first queued job whose room is missing),
        where this worker waits for none of its own: adopt it, or the next job's when the one it followed waits no
        more; with none left, an adopted wait ends at once (claims succeed again: its job was claimed, settled or
        removed, or its room made), not at its own time, up to an hour later."""
        if waiting is not None:
            if waiting[0] != self._adopted:
                self._adopt_wait(*waiting)
            return
        if self._adopted is None or self._room_again():  # its room, or its time: said as the wait's end
            return
        self.log(f"{self._adopted} waits for room in the queue no more (claimed, settled or removed): claiming jobs "
                 f"again")
        self.room, self._adopted = None, None

    def _adopt_wait(self, job_id: str, note: dict) -> None:
        """Wait, as the worker that gave it back does, for the room that the queued job `job_id` waits for (its
        record's note, `Queue.room_wait`, its folder found under this worker's queue or root): no claim would be
        taken until then. Said once."""
        wait = RoomWait.from_note(note, job_id, roots=self.queue.roots)
        if wait is not None:
            self.room, self._adopted = wait, job_id
            self.log(wait.adopted_line(self.config.poll_s))

    def _say_doubts(self, doubts: list[tuple[str, str]]) -> None:
        """Say once of each queued job's wait that is read otherwise than it says (`Queue.room_wait`'s `doubts`:
        a wait from a clock running ahead, or one longer than any worker waits) how it is read."""
        for doubt in doubts:
            if doubt not in self._doubts_said:
                self._doubts_said.add(doubt)
                self.log(f"{doubt[0]} went back to the queue on a full disk, but {doubt[1]}")

    def _room_again(self) -> bool:
        """Whether the wait for room is over (`RoomWait.over`), said when it is; a probe that fails is said once and
        the wait goes on."""
        room = self.room
        what = f"check the free space on {room.mount}"
        try:
            over, free = room.over()
        except OSError as exc:  # the timer still ends the wait
            self._trouble(what, exc)
            if not room.timed_out():
                return False
            over, free = True, None
        else:
            self._trouble(what, None)
        if not over:
            return False
        self.room, self._adopted = None, None
        self.log(room.ended_line(free))
        return True

    def _say_queued(self, claim: Claim, why: str) -> None:
        """A live job about to go back to the queue says so in its live status (`mark_live_queued`) while this worker
        still holds it: once in queued/, another worker may claim it and its attempt write its first status at once,
        over which a note written after would stand (for a rerun of a complete scan, its whole final run). The lease
        is renewed first, so that no other worker can take the job over before the note is written; a lease already
        lost (the job is another worker's) leaves the status to that worker's attempt."""
        if not claim.job.live:
            return
        try:
            held = self.queue.heartbeat(claim)
        except OSError:  # the queue unreachable for a moment: what release/crash meet next says where the job is
            return
        if held:
            mark_live_queued(claim.job, self.root, why, self.log)

    def _record_waiting(self) -> None:
        """Write the attempt records of ended jobs that a full disk kept out (`_settle_error`)."""
        for job_id, (claim, values) in list(self.unrecorded.items()):
            try:
                self.queue.write_outcome(claim, values)
            except OSError as exc:
                self._trouble(_recording(job_id), exc)
                continue
            del self.unrecorded[job_id]
            self._trouble(_recording(job_id), None)

    def _gave_up(self, job_id: str) -> None:
        """Settle a job that this worker's `reclaim_expired` moved to failed/ (its worker died on its last attempt)
        as `_settle_error` settles one whose process died under this worker: counted as failed, and a live job's
        status says stopped. A job no longer in failed/ was settled otherwise meanwhile (the finished result its dead
        worker left was published by `_reconcile`, or it was retried by hand)."""
        path = self.queue.path / "failed" / f"{job_id}.json"
        if not path.exists():
            return
        self.settled[job_id] = "failed"
        job = self.queue.job_in("failed", job_id)
        if job is not None:
            self._settle_failed(job, self.queue.last_error(job_id) or "its worker died on the job's last attempt")

    def _settle_failed(self, job, error: str) -> None:
        """The queue gave up on `job`: a live job's status must not go on saying it is finishing."""
        self.settled[job.id] = "failed"
        if job.live:
            mark_live_failed(job, self.root, error, self.log)

    def _settle_done(self, child: Child, seconds: float, summary: dict) -> None:
        self._publish(Unpublished(child, seconds, summary))

    def _publish(self, waiting: Unpublished) -> bool:
        """Publish a finished job's result and say so; True once that is settled (published, or dropped because the
        lease was lost). A write that fails (a full disk) keeps the job in `unpublished`, its scratch folder whole:
        said once, tried again at the next poll."""
        child = waiting.child
        job = child.claim.job
        what = f"publish the finished result of {job.id} ({child.scratch})"
        try:
            published = self._publish_once(child)
        except OSError as exc:
            self.unpublished[job.id] = waiting
            self._trouble(what, exc)
            return False
        self.unpublished.pop(job.id, None)
        self._trouble(what, None)
        if published is None:
            self._lease_lost(job.id, child, self._removed(child) or "its lease had been taken over")
            return True
        self._said_done(waiting, *published)
        return True

    def _publish_once(self, child: Child) -> tuple[Path, Path | None] | None:
        """publishing.publish_claim, or, when an earlier try got as far as renaming the result into place (a full disk
        met while the queue's record was written), the rest of it: the job recorded as done with that result."""
        claim = child.claim
        final = result_path(claim.job, self.root)
        if self._in_place(child):
            if claim.path.exists():
                if not self.queue.finish(claim, str(final)):
                    return None
            elif self._done_in_place(child):  # moved to done/ already: only its attempt record was left to complete
                self.queue.record_done(claim.job.id, str(final))
            else:
                return None  # taken over: the job's next claim records it as done with this result
            return final, None
        return publish_claim(self.queue, claim, child.scratch, final, child.log)

    def _in_place(self, child: Child) -> bool:
        """Whether this claim's result has been renamed into place (its marker names this claim): its job file is
        in done/ or on its way there, not lost to another worker; only the queue's record is left to write, which
        `_publish_once` does once it fits."""
        final = result_path(child.claim.job, self.root)
        return not child.scratch.exists() and (completion(final) or {}).get("token") == child.claim.token

    def _done_in_place(self, child: Child) -> bool:
        """Whether this claim's result is in place and its job file in done/: published, only the queue's record
        left to write (the lease is not lost: the file left running/ for done/)."""
        return self._in_place(child) and (self.queue.path / "done" / f"{child.claim.job.id}.json").exists()

    def _publish_waiting(self) -> None:
        for waiting in list(self.unpublished.values()):
            self._publish(waiting)

    def _drop_unpublished(self, job_id: str, why: str) -> None:
        waiting = self.unpublished.pop(job_id)
        self._troubles.pop(f"publish the finished result of {job_id} ({waiting.child.scratch})", None)
        self._lease_lost(job_id, waiting.child, f"{why} before its result could be published")

    def _removed(self, child: Child) -> str:
        """For a claim whose file is gone from running/: when no other worker took the job over (its file was
        removed by hand), the job is put in failed/ (`Queue.restore_removed`) and settled as failed, and this says
        so ('' otherwise)."""
        reason = "its file in running/ was removed while it ran (by hand?)"
        if not self.queue.restore_removed(child.claim, reason):
            return ""
        self._settle_failed(child.claim.job, reason)
        return (f"{reason}: the job is in failed/ "
                f"(`{worker_command(self.root, self.queue.path, '--retry-failed')}` queues it again)")

    def _lease_lost(self, job_id: str, child: Child, why: str) -> None:
        """Say what became of a finished result whose lease was taken over: dropped while still in its scratch
        folder (the job is another worker's now), kept when it had been renamed into place already (the job's next
        claim finds its own result there and records the job as done)."""
        if self._in_place(child):
            final = result_path(child.claim.job, self.root)
            self.log(f"{job_id}: finished and its result is in place at {final}, but {why}; the worker that claims "
                     f"the job next records it as done")
            return
        shutil.rmtree(child.scratch, ignore_errors=True)
        self.log(f"{job_id}: finished, but {why}; result dropped")

    def _said_done(self, waiting: Unpublished, final: Path, aside: Path | None) -> None:
        """Record a published job as done and log its done line."""
        job, seconds, summary = waiting.child.claim.job, waiting.seconds, waiting.summary
        if job.live:
            mark_live_done(job, self.root, final, self.log)
        self.settled[job.id] = "done"
        self._full_in_row = 0
        extra = f", Chamfer {summary['chamfer_mm']:.2f} mm" if isinstance(summary.get("chamfer_mm"), float) else ""
        if summary.get("ground_truth_note"):
            extra += f" (ground truth: {summary['ground_truth_note']})"
        if summary.get("converged") is False:
            extra += ", not converged"
        # One message, so that no other line lands between the done line and its warnings.
        self.log(f"{job.id} done in {seconds:.1f} s{extra} -> {final}" + _warning_lines(summary))
        if aside is not None:  # written there while the job ran (another worker on another queue, say)
            self.log(f"{job.id}: {final} held a result that appeared while the job ran; moved it to {aside}")

    # ---- stopping --------------------------------------------------------------------------------------------
    async def _shutdown(self) -> None:
        """Stop every child (SIGTERM, then SIGKILL after the grace period) and give its job back to the queue; try
        once more to publish the finished results still waiting (`_leave_unpublished`)."""
        try:
            await self._stop_children()
        finally:
            if self.unpublished:
                await asyncio.to_thread(self._leave_unpublished)
            if self.unrecorded:
                await asyncio.to_thread(self._leave_unrecorded)

    async def _stop_children(self) -> None:
        if not self.children:
            return
        for child in self.children.values():
            kill_group(child.proc, signal.SIGTERM)
        waits = [c.wait for c in self.children.values()]
        await asyncio.wait(waits, timeout=self.config.stop_grace_s)
        for child in self.children.values():
            if not child.wait.done():
                kill_group(child.proc, signal.SIGKILL)
        await asyncio.gather(*waits, return_exceptions=True)
        for job_id, child in self.children.items():
            # its process is gone (waited for above): nothing of this attempt writes the status after this
            if self._give_back(child.claim, "worker stopped", said="its worker was stopped"):
                self.log(f"{job_id} stopped; back in the queue")
            child.outcome.unlink(missing_ok=True)
            shutil.rmtree(child.scratch, ignore_errors=True)
        self.children.clear()

    def _give_back(self, claim: Claim, reason: str, said: str | None = None) -> bool:
        """queue.release, the one way this worker gives a job it holds back to the queue; True also when only its
        record failed on a full disk: the job file went back to queued/ (a rename needs no room), its record could
        not say why. A live job says it is queued again first (`_say_queued`, `said`: why, default `reason`), while
        this worker still holds it."""
        self._say_queued(claim, said or reason)
        try:
            return self.queue.release(claim, reason)
        except OSError:
            return True

    def _leave_in_place(self, job_id: str, child: Child) -> None:
        """A stopping worker's result that was renamed into place, its job not yet recorded as done (a full disk):
        nothing is reconstructed again; the job's next claim (or, for a job already in done/, the next worker to
        start) records it as done with that result."""
        final = result_path(child.claim.job, self.root)
        if self._done_in_place(child):
            self.log(f"{job_id} stopped before its attempt record could say done; the job is done, its result in "
                     f"place at {final} (the next worker to start completes the record)")
            return
        if self._give_back(child.claim, "worker stopped before it could record the job as done"):
            self.log(f"{job_id} stopped before the queue recorded it as done; back in the queue, its result is in "
                     f"place at {final}: the next worker to claim it records the job as done, not reconstructing "
                     f"it again")

    def _leave_unrecorded(self) -> None:
        """A worker that stops while attempt records wait to be written tries each once more; the job's state is
        right either way (its file moved), only the record's error is missing, and this worker's line named it."""
        self._record_waiting()
        for job_id, (claim, values) in self.unrecorded.items():
            self.log(f"{job_id}: stopped before its attempt record could be written; the record goes on saying "
                     f"running, the job ended: {values.get('error')}")
        self.unrecorded.clear()

    def _leave_unpublished(self) -> None:
        """A worker that stops while finished results wait to be published tries each once more. One that still
        cannot be published is marked complete without its log (the queue's logs/ keeps it), so that the next worker
        to start publishes it (publishing.reconcile), and its job is given back to the queue; only when not even the
        marker can be written is the result lost, and the line says that the job will run again."""
        self._publish_waiting()
        for job_id, waiting in list(self.unpublished.items()):
            child = waiting.child
            if self._in_place(child):
                del self.unpublished[job_id]
                self._leave_in_place(job_id, child)
                continue
            try:
                mark_complete(child.scratch, job_id, child.claim.token, self.queue.path)
                kept = f"its finished result stays in {child.scratch}, for the next worker to publish"
            except OSError as exc:
                shutil.rmtree(child.scratch, ignore_errors=True)
                kept = (f"its finished result could not be kept ({fold(exc)}): it will be "
                        f"reconstructed again")
            del self.unpublished[job_id]
            if self._give_back(child.claim, "worker stopped before it could publish the result"):
                self.log(f"{job_id} stopped before its result could be published; back in the queue, {kept}")


def _full_folder(child: Child, outcome: dict) -> Path:
    """The folder a job's process met a full disk in: its outcome's, or, where the outcome file itself did not fit,
    the folder that file was written into (the queue's tmp/) when that is on a disk of its own (`--queue`), else its
    result's, which it filled. A folder in the scratch folder, which is removed, is named by the scan's recon/ folder
    it was in."""
    if not outcome and not same_filesystem(child.outcome.parent, child.scratch):
        return child.outcome.parent
    folder = Path(outcome.get("folder") or child.scratch)
    if folder == child.scratch or child.scratch in folder.parents:
        folder = child.scratch.parent
    return folder


def _report_summary(scratch: Path) -> dict:
    """A finished job's summary (`jobs.summary_of`) read from its report.json, for a job whose outcome file did not
    fit; {} when it cannot be read (the done line then says less)."""
    try:
        report = json.loads((scratch / "report.json").read_text())
    except (OSError, ValueError):
        return {}
    return summary_of(report) if isinstance(report, dict) else {}


def _wait_key(note: dict | None) -> tuple | None:
    """What tells one wait for room from another (a presence file is rewritten when it changes)."""
    return None if note is None else (note.get("mount"), note.get("since_unix"))


def _warning_lines(summary: dict) -> str:
    """A done line's warnings, each on a line of its own, indented under it ("\\n  warning: ..."); '' when there are
    none. A report's warnings run to about ten, a sentence or two each: on the done line they made it thousands of
    characters long."""
    warnings = list(summary.get("warnings") or [])
    counts_note = summary.get("capture_counts_note")
    if counts_note and counts_note not in warnings:  # a report's warnings carry it now
        warnings.insert(0, counts_note)
    return "".join(f"\n  warning: {warning}" for warning in warnings)


def _not_queued(name: str, settling_s: float | None) -> str:
    """What a worker run with --once says of a scan it leaves: one still recorded, or one that looks like a copy
    still under way, queued only once nothing in it has changed for `watcher.SETTLE_S` (`settling_s` from now)."""
    if settling_s is None:
        return (f"not queued: scan {name} is still being recorded (a worker without --once takes it when it ends; "
                f"with --live, as it is recorded)")
    changed = max(0.0, SETTLE_S - settling_s)
    return (f"not queued: scan {name} looks like a copy still under way (something in it changed {changed:.0f} s "
            f"ago): it is taken once nothing in it has changed for {SETTLE_S:.0f} s, in {math.ceil(settling_s)} s if "
            f"it stays as it is; run the worker again then, or without --once")


def _left_why(settling_s: float | None) -> str:
    """Why a worker run with --once left a scan, in a few words (its summary line names each one left): `_not_queued`
    says it in full."""
    if settling_s is None:
        return "still being recorded"
    return (f"a copy still under way: taken once nothing in it has changed for {SETTLE_S:.0f} s, in "
            f"{math.ceil(settling_s)} s")


def _recording(job_id: str) -> str:
    """What `_trouble` says the worker could not do while an ended job's attempt record does not fit."""
    return f"write the attempt record of {job_id}"


def _moved_to(state: str, bad_input: bool) -> str:
    """Where a job that ended in error went, as its line says."""
    if state == "queued":
        return "queued again"
    return "moved to failed/" if bad_input else "giving up (moved to failed/)"


def _shown(value) -> str:
    """A job option's value as a log line shows it (None: the preset's default)."""
    return "default" if value is None else str(value)


@dataclass(frozen=True)
class WorkerRun:
    """What a worker run did, for its command's summary line and exit status."""

    settled: dict[str, str]
    """Job id -> 'done', 'failed' or 'kept' (`Worker.settled`)."""
    left: dict[str, str]
    """With `once`: scan -> why it was left unqueued (`Worker.left`)."""
    untakeable: dict[str, str] = field(default_factory=dict)
    """Queued jobs this worker may not take -> why (`Worker.untakeable`)."""


async def run_worker(config: WorkerConfig, log: Callable[[str], None] | None = None,
                     handle_signals: bool = True, progress_s: float | None = PROGRESS_S) -> WorkerRun:
    """Run a worker until SIGINT/SIGTERM (or drained, with `once`), saying each running job's progress every
    `progress_s` seconds (None: never)."""
    worker = Worker(config, log, progress_s)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    sigs = (signal.SIGINT, signal.SIGTERM) if handle_signals else ()
    for sig in sigs:
        loop.add_signal_handler(sig, stop.set)
    try:
        settled = await worker.run(stop)
    finally:
        for sig in sigs:
            loop.remove_signal_handler(sig)
    return WorkerRun(dict(settled), dict(worker.left), dict(worker.untakeable))


__all__ = ["Worker", "WorkerRun", "run_worker"]
