"""Watch a captures root and reconstruct every complete scan, once, in child processes.

Every child folder of ROOT that holds scan.json in state 'complete' becomes the job `<scan>-<preset>` in a durable
queue (ROOT/.queue by default; a scan name with characters other than A-Za-z0-9._- gets a short hash in its id, so
that no two scans share one). Several workers, on this machine or on others sharing the folder, can serve one root:
each job runs exactly once; a job whose worker died is taken over when its lease expires (at once on the same
machine) and retried up to --max-attempts times. A malformed capture fails its job with the reason, never the worker.
Results go to <scan>/recon/<job>/ (mesh.ply, report.json, pictures, job.log). Ctrl-C or SIGTERM stops the job
processes and gives their jobs back to the queue.

A result is never replaced in silence: a job whose <scan>/recon/<job>/ already holds one (from another queue, or
from before the queue was deleted) is not run; it is recorded as done, and the log and --status say so. To
reconstruct finished scans again, `--redo JOB...` moves each one's results folder aside to
<scan>/recon/<job>.replaced-<UTC time>-<4 hex digits>/, queues the job again and exits: a worker on that root and
queue (a running one, or one started with --once) then reconstructs it.

--budget-s bounds each job's whole run, from its process's start to its report (within 10 % or 10 s, whichever is
larger): the mesh is coarser and the metrics use fewer points when time is short. --status shows, for each done
job, whether its reconstruction converged and the warnings its report gives (a run cut short, starved of CPU, or
whose fit does not explain the measurements, a 3D view that could not be written).

Options are frozen into each job when it is queued: --budget-s, --steps, --device and --seed apply to the scans a
worker queues, and a job already queued (by this worker or an earlier one) runs with its own (the worker names, when
it starts and whenever it queues a job again, the queued jobs whose own values differ from the ones given). To run
failed jobs again with other options, give them with --retry-failed: `--retry-failed --device cpu` queues every
failed job again with device cpu, and the options not given keep each job's own values. The preset is part of a
job's id, so with --retry-failed, --preset picks the failed jobs of that preset. Bad options (--device cuda where
torch sees no GPU, a negative --seed) are refused before anything is queued.

Each job process gets --threads CPU threads (OMP_NUM_THREADS): by default the worker's own OMP_NUM_THREADS when it
is set, else the machine's cores shared out among --processes and the job processes of the other workers on this
machine (each one's --processes, idle or not, read from their files under QUEUE/workers/; workers on other machines
sharing the queue do not count). Jobs that together ask for more threads than there are cores stall each other (two
2-thread jobs on 2 cores run 20-40x slower per step than two 1-thread ones): the worker warns when the job processes
on this machine x threads are more than the cores. It says at start-up, and when a job starts beside other workers
than the last one did, which workers share the cores and what each job gets, e.g. `another worker runs on this host
(pid 4242, 1 job process(es)): 1 CPU threads per job (OMP_NUM_THREADS=1: 2 cores shared out among 2 job
process(es)); one worker with --processes 2 does the same with less: ...`; the job's log (the result's job.log)
begins with that line. --threads and an OMP_NUM_THREADS of the worker's own are kept beside other workers. An
OMP_NUM_THREADS that is not a whole number >= 1 is ignored, with a warning.

--live reconstructs while the arm scans: a scan is queued as soon as its first chunk is published, and its job
follows it (each new chunk is read as it lands; the views in use grow, nothing restarts). Every few seconds it
publishes <scan>/recon/live/ (mesh.ply, preview.png, status.json with views_used, views_published, steps,
updated_utc, converged and, with a ground truth, chamfer_mm; `spadscan ctl status` shows it). When the scan is
complete the job finishes from the live state (--budget-s bounds that final run; by default it polishes the live fit
for about 4 s of steps, or, when the live fit is still on its coarse level or only just past it, or the scan ended
with the fit a quarter behind the views it holds or more, fits from the carved hull for the preset's budget), and
publishes its result where every job does. An aborted scan's live job ends (failed, with the scan's reason; the live
folder keeps its last state). A live job holds its job process from the
scan's first chunk to its end: give the worker a process for each scan that may run at once (--processes). Live
jobs run the fast preset. A scan's recon/live/ is one live job's, the first claimed: another live job of the scan
(another queue's on the same root) waits in the queue while the scan is recorded, holding no worker (--status says
so), and then reconstructs the scan as an ordinary job, its budget counted from its start.

A job is recorded as done only once its result is in place, so a worker killed at any moment loses nothing: the
next worker to start reconciles the queue with the result folders. It publishes the finished result a dead worker
left in a scratch folder (<scan>/recon/.tmp-<job>-<claim>/, complete once its marker .complete is written), records
as done a job whose result is in place, removes partial results, and queues again a done job whose result is gone.
A full disk while a finished result is published (its log copied in, its marker written) loses nothing either: the
worker keeps the result and the job's claim, says so once, and publishes it when there is room again, while its
other jobs run on; a worker stopped meanwhile leaves it marked complete, and the next worker to claim the job
publishes it instead of reconstructing it again. A job whose own process meets a full disk is not at fault: its
partial result is removed, it goes back to the queue without using an attempt, the worker's line names the folder
that could not be written and the filesystem to make room on, and the worker claims no job until there is room (it
checks the free space every --poll-s, and claims again after 10 minutes all the same, 20, 40, then every hour while
jobs keep meeting it), saying so when it stops and when it goes on. The disk named is the one that is full: the
queue's (--queue on a disk of its own) when the job's log or outcome file did not fit there. A full disk quota
(EDQUOT) does not show in the free space: the worker says it is a quota and waits for the timer alone. The job's
attempt record carries the wait, and no worker on the queue claims a job while it lasts: another worker waits too,
says so, and goes on once that job no longer waits in the queue. Such a wait lasts an hour at most, whatever the
record or another machine's clock says; its folder is found under this worker's own root or queue, else it is waited
for on its timer. A job that finished, whose small outcome file alone did not fit, is published, not reconstructed
again. A job that met a full disk 3 times fails: its result may need more room than the disk frees; make room, then
--retry-failed.

While it runs, the worker says each running job's progress in its own terminal, one line per job, when the job's
stage changes (its training starts or ends) and every 30 s in between; a job's done line is followed by its report's
warnings, one indented line each.

--status lists the jobs and changes nothing. A running job shows how far it has got (its progress bar: seconds of
its budget or steps, the step, the loss and, where the scene is known, the last checkpoint's Chamfer; --json:
`progress`); a done job, its result and its report's warnings, each on a line of its own. A running job whose worker
died or stopped renewing its lease shows as
`stale` (the next worker to look at the queue takes it over); one whose worker has missed heartbeats while its lease
still holds shows as `running?`. Its last line (not with --json, which lists the jobs alone) names the workers
running on the queue, idle ones included (each renews a file under QUEUE/workers/ while it runs), and where a worker
waits for room on a full disk, where and until when at the latest (in UTC); or it says that no worker runs and how
to start one.

--once queues the complete scans there are, runs until nothing is queued or running, and exits. Its last line
counts the jobs done and failed and names each scan it left unqueued, and why (still recorded, or a copy still under
way: taken once nothing in it has changed for 60 s), and each queued job it may not take (another user's on a
shared queue), left for a worker that may. Its exit status: 0, 1 when a job failed, 130 when it was stopped before
the queue drained, 75 when it ran no job while it left scans or jobs waiting (run it again later). Without
--once the worker runs until Ctrl-C or SIGTERM (`systemctl stop`), says what it settled meanwhile, and exits 0: a
service stopped as asked.

Examples:
  spadscan worker --root captures --processes 2
  spadscan worker --root captures --once          # reconstruct what is there, then exit
  spadscan worker --root captures --live          # reconstruct scans while they are recorded
  spadscan worker --root captures --status        # list jobs: state, attempts, last error, result
  spadscan worker --root captures --retry-failed  # put failed jobs back in the queue, with their own options
  spadscan worker --root captures --retry-failed --device cpu   # ... to run on the CPU
  spadscan worker --root captures --redo mug-fast --steps 400    # queue a finished scan again (a worker reruns it)
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--root", required=True, metavar="CAPTURES", help="captures root whose children are scans")
    parser.add_argument("--processes", type=int, default=None, metavar="N", help="jobs run at once (default: 1)")
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="CPU threads per job, given to each job as OMP_NUM_THREADS; default: the worker's own "
                             "OMP_NUM_THREADS when set, else the machine's cores shared out among --processes and "
                             "the job processes of the other workers on this machine, at least 1 (the start-up line "
                             "says how many)")
    parser.add_argument("--preset", default=None,
                        help="reconstruction preset: fast or paper (default: fast; with --retry-failed: only the "
                             "failed jobs of this preset)")
    parser.add_argument("--budget-s", type=float, default=None, metavar="S",
                        help="seconds per job, from the job's start to its report (set-up, training, mesh, metrics "
                             "and pictures), as `spadscan reconstruct --budget-s` (default: the preset's)")
    parser.add_argument("--steps", type=int, default=None, metavar="N",
                        help="optimisation steps per reconstruction (default: the preset's)")
    parser.add_argument("--device", default=None, choices=("auto", "cpu", "cuda"),
                        help="where reconstructions run (default: auto)")
    parser.add_argument("--seed", type=int, default=None, help="random seed of the reconstructions (default: 0)")
    parser.add_argument("--once", action="store_true",
                        help="queue the complete scans there are, run until nothing is queued or running, exit "
                             "(status 1 when a job failed, 130 when stopped before the queue drained, "
                             f"{LEFT_WAITING} when it ran no job while it left scans it could not queue yet: still "
                             "recorded, or a copy still under way; the last line names them and why)")
    parser.add_argument("--live", action="store_true",
                        help="start each scan's reconstruction at its first published chunk and follow the scan, "
                             "publishing <scan>/recon/live/ every few seconds; --budget-s then bounds the final run "
                             "after the scan ends (default: about 4 s of steps polishing the live fit; fast preset "
                             "only)")
    parser.add_argument("--poll-s", type=float, default=None, metavar="S",
                        help="seconds between looks at the root and the queue (default: 2)")
    parser.add_argument("--lease-s", type=float, default=None, metavar="S",
                        help="a job whose worker has not renewed its lease for S seconds is taken over (default: 60)")
    parser.add_argument("--max-attempts", type=int, default=None, metavar="N",
                        help="tries of a job whose process or worker died before it fails (default: 3)")
    parser.add_argument("--queue", default=None, metavar="DIR", help="queue folder (default: ROOT/.queue)")
    parser.add_argument("--status", action="store_true",
                        help="list the jobs and exit (changes nothing; only --queue, --json and --lease-s go with "
                             "it): a running job with its progress; one whose worker seems gone shows as 'stale' or "
                             "'running?'; its last line (not with --json) names the workers running, idle ones "
                             "included, and says where one waits for room on a full disk, and until when")
    parser.add_argument("--json", action="store_true", help="with --status: print JSON instead of a table")
    parser.add_argument("--retry-failed", action="store_true",
                        help="put every failed job back in the queue with a fresh attempt count, and exit; "
                             "--budget-s, --steps, --device and --seed given with it replace the jobs' own values "
                             "(the others are kept)")
    parser.add_argument("--redo", nargs="+", default=None, metavar="JOB",
                        help="queue these done jobs again, and exit (a worker on the root and queue then reconstructs "
                             "them): each one's results folder is moved aside to <scan>/recon/<job>.replaced-<UTC "
                             "time>-<4 hex digits>/ (never deleted; the new name is printed); --budget-s, --steps, "
                             "--device and --seed given with it replace the jobs' own values (the others are kept)")


OPTION_FLAGS = {"budget_s": "--budget-s", "steps": "--steps", "device": "--device", "seed": "--seed"}
"""Job options that can be given on the command line, and their flags. None in `args` means not given."""

RUN_FLAGS = {"once": "--once", "processes": "--processes", "threads": "--threads", "poll_s": "--poll-s",
             "max_attempts": "--max-attempts", "live": "--live"}
"""Flags that only say how the worker runs jobs: meaningless with --status and --retry-failed, which run none."""

LEFT_WAITING = 75
"""Exit status of --once when it ran no job while it left scans it could not queue yet (sysexits' EX_TEMPFAIL: try
again later)."""

DEFAULTS = {"processes": 1, "poll_s": 2.0, "lease_s": 60.0, "max_attempts": 3}
"""Values of the flags left out (their default is None in `args`, so that a flag given can be told from one not)."""


def run(args) -> int:
    import asyncio
    from pathlib import Path

    from spadscan.worker.pool import run_worker
    from spadscan.worker.queue import QUEUE_DIRNAME, Queue
    from spadscan.worker.watcher import JobOptions, check_root
    from spadscan.worker.worker_config import WorkerConfig

    _refuse_combinations(args)
    root = check_root(args.root)
    queue_dir = Path(args.queue) if args.queue else root / QUEUE_DIRNAME
    _check_queue(queue_dir, given=args.queue is not None, creates=not args.status)
    lease_s = DEFAULTS["lease_s"] if args.lease_s is None else args.lease_s
    if args.status:  # a query: a root without a queue yet is listed as empty, not given one
        return _print_status(Queue(queue_dir, lease_s=lease_s, create=False, root=root), args.json, root)
    given = _given_options(args)
    _check_limits(given)
    if args.retry_failed:
        return _retry_failed(Queue(queue_dir, create=False), given, args.preset, root)
    if args.redo:
        return _redo(Queue(queue_dir, create=False), root, args.redo, given)
    options = JobOptions(**({"preset": args.preset} if args.preset else {}), **given, live=args.live)
    value = {key: DEFAULTS[key] if getattr(args, key) is None else getattr(args, key) for key in DEFAULTS}
    config = WorkerConfig(
        root=root, processes=value["processes"], queue_dir=queue_dir, poll_s=value["poll_s"], lease_s=lease_s,
        max_attempts=value["max_attempts"], once=args.once, threads=args.threads, options=options,
        options_given=tuple(given),
    )
    ran = asyncio.run(run_worker(config))  # checks the config (options included) before queuing anything
    settled = ran.settled
    if not args.once:  # a service stopped as asked (Ctrl-C, SIGTERM: `systemctl stop`) ends well: 0
        print(f"spadscan worker: stopped; {_settled_note(settled)} while it ran")
        return 0
    failed = any(s == "failed" for s in settled.values())
    kept = sum(1 for s in settled.values() if s == "kept")
    # Stopped (Ctrl-C, SIGTERM) before the queue drained: said, and not the exit status of a drained queue.
    queue = Queue(queue_dir, create=False)
    # The queued jobs this worker may not take (another user's) are left for a worker that may: named, not waited for.
    queued = queue.queued_ids()
    untakeable = {job: why for job, why in ran.untakeable.items() if job in queued}
    counts = queue.counts()
    unfinished = counts.get("queued", 0) - len(untakeable) + counts.get("running", 0)
    print(f"spadscan worker: {_settled_note(settled)}"
          + (f", {kept} not run (their results were already there)" if kept else "")
          + (f"; stopped with {unfinished} job{'s' if unfinished != 1 else ''} still queued or running"
             if unfinished else "")
          + _left_note(ran.left) + _untakeable_note(untakeable))
    if unfinished:
        return 130
    if failed:
        return 1
    # No job settled while scans or jobs wait (a copy still under way, a scan still recorded, another user's job):
    # a script runs it again later.
    return LEFT_WAITING if (ran.left or untakeable) and not settled else 0


def _settled_note(settled: dict[str, str]) -> str:
    """'2 done, 1 failed (x-fast)': what a run settled, for its last line."""
    done = sum(1 for s in settled.values() if s == "done")
    failed = sorted(j for j, s in settled.items() if s == "failed")
    return f"{done} done, {len(failed)} failed" + (f" ({', '.join(failed)})" if failed else "")


def _left_note(left: dict[str, str], most: int = 5) -> str:
    """What the summary line of --once says of the scans the run left unqueued, each with why; '' when none."""
    if not left:
        return ""
    named = [f"{name} ({why})" for name, why in list(left.items())[:most]]
    more = f" and {len(left) - most} more" if len(left) > most else ""
    return f"; left {len(left)} scan{'s' if len(left) != 1 else ''} not queued yet: {', '.join(named)}{more}"


def _untakeable_note(untakeable: dict[str, str], most: int = 3) -> str:
    """What the summary line of --once says of the queued jobs it may not take, each with why; '' when none."""
    if not untakeable:
        return ""
    named = [f"{job} ({why})" for job, why in list(untakeable.items())[:most]]
    more = f" and {len(untakeable) - most} more" if len(untakeable) > most else ""
    return (f"; left {len(untakeable)} queued job{'s' if len(untakeable) != 1 else ''} it may not take, for a worker "
            f"that may: {', '.join(named)}{more}")


def _refuse_combinations(args) -> None:
    """Flags that would be ignored in this combination are an error, not a surprise later."""
    from spadscan.protocol.errors import ConfigError

    if args.json and not args.status:
        raise ConfigError("--json goes only with --status (it prints the job list as JSON)")
    if args.status:
        extra = {**RUN_FLAGS, **OPTION_FLAGS, "preset": "--preset", "retry_failed": "--retry-failed",
                 "redo": "--redo"}
        action = "--status only lists the jobs"
    elif args.redo:
        extra = {**RUN_FLAGS, "lease_s": "--lease-s", "retry_failed": "--retry-failed", "preset": "--preset"}
        action = "--redo only queues the done jobs it names again and exits (their ids name their preset)"
    elif args.retry_failed:
        extra = {**RUN_FLAGS, "lease_s": "--lease-s"}
        action = "--retry-failed only queues failed jobs again and exits (run the worker after it)"
    else:
        return
    given = [flag for key, flag in extra.items() if getattr(args, key) not in (None, False)]
    if given:
        raise ConfigError(f"{action}: {', '.join(given)} {'does' if len(given) == 1 else 'do'} not go with it")


def _check_queue(queue_dir, given: bool, creates: bool) -> None:
    """Refuse, in one line that names --queue, a queue folder that cannot be one: a capture or a folder inside one
    (its files would be mixed into the measurements), a file there or above it; for all but --status (`creates`: a
    run makes the folder and writes its jobs into it, --redo and --retry-failed write the jobs they queue again), one
    that cannot be made or written into; for --status with a --queue given (it would end by suggesting a worker on
    it), one that is not there and cannot be made (one that is there is only read). A root's default queue that is
    missing is only read by --status: it lists it as empty, since the root's own worker makes it, even where this
    user cannot."""
    from spadscan.protocol.capture_format import MANIFEST, enclosing_capture
    from spadscan.protocol.folders import folder_problem, not_a_folder
    from spadscan.protocol.errors import ConfigError

    name = f"--queue {queue_dir}" if given else f"queue {queue_dir}"
    capture = enclosing_capture(queue_dir)
    if capture is not None:
        where = "is a capture" if capture == queue_dir.resolve() else f"lies inside the capture {capture}"
        raise ConfigError(f"{name} {where} (it holds {MANIFEST}): the queue's folders would be mixed into its "
                          f"measurements; choose a folder outside it")
    reason = folder_problem(queue_dir, writable=creates) if creates or given else not_a_folder(queue_dir)
    if reason is None:
        return
    if not queue_dir.is_dir() and (queue_dir.exists() or queue_dir.is_symlink()):  # in the dashboard's words
        raise ConfigError(f"{name}: no such queue folder ({reason})")
    raise ConfigError(f"{name}: {reason}")


def _given_options(args) -> dict:
    """The job options given on the command line (the ones left out stay at their defaults, or at a failed job's
    own values with --retry-failed)."""
    return {key: getattr(args, key) for key in OPTION_FLAGS if getattr(args, key) is not None}


def _check_limits(given: dict) -> None:
    """Refuse run limits out of bounds among the options `given` (`_given_options`), in one line that names the
    flag (the jobs' own check, which names none, would say the same later)."""
    from spadscan.protocol.errors import ConfigError
    from spadscan.worker.jobs import run_limits_problem

    problem = run_limits_problem(given.get("budget_s"), given.get("steps"), given.get("seed", 0), flags=True)
    if problem:
        raise ConfigError(problem)


def _retry_failed(queue, given: dict, preset: str | None, root: Path) -> int:
    """Queue failed jobs again (those of `preset`, if given), with the options `given` on the command line."""
    from spadscan.worker.watcher import JobOptions

    JobOptions(**({"preset": preset} if preset else {}), **given).check()  # before any job moves
    for job in _jobs_in(queue, "failed", preset):
        _say_queued(job, root, "queued again by `spadscan worker --retry-failed`")
    moved = queue.retry_failed(changes=given, preset=preset)
    changed = ", ".join(f"{OPTION_FLAGS[k]} {v}" for k, v in given.items())
    if not moved:
        print("no failed jobs" + (f" of preset {preset}" if preset else ""))
    else:
        print(f"queued again: {', '.join(moved)}" + (f" (with {changed})" if changed else " (with their own options)"))
    return 0


def _redo(queue, root, job_ids: list[str], given: dict) -> int:
    """Queue done jobs again, each one's results folder moved aside first: a worker keeps a result it finds."""
    from spadscan.protocol.errors import ConfigError
    from spadscan.worker.jobs import move_aside, result_path
    from spadscan.worker.watcher import JobOptions

    JobOptions(**given).check()  # before any folder moves
    jobs = [_done_job(queue, job_id) for job_id in dict.fromkeys(job_ids)]
    changed = ", ".join(f"{OPTION_FLAGS[k]} {v}" for k, v in given.items()) or "their own options"
    for job in jobs:
        aside = move_aside(result_path(job, root))  # a done job's result is in place: it is published first
        said = _say_queued(job, root, "queued again by `spadscan worker --redo`"
                           + (f"; its earlier result is now {aside}" if aside else ""))
        if not queue.requeue("done", job.id, changes=given):
            _unsay_queued(queue, job, root, said)
            raise ConfigError(f"{job.id}: another process moved the job while it was being queued again"
                              + (f"; its earlier result is in {aside}" if aside else ""))
        kept = f"; its earlier result is now {aside}" if aside else "; it had no results folder"
        print(f"queued again: {job.id} (with {changed}){kept}")
    return 0


def _say_queued(job, root: Path, why: str) -> tuple[bytes, bytes] | None:
    """A live job queued again says so in its live status ('queued', `why`): its 'done' or 'stopped' would stand
    until a worker claims the job, over figures of a result moved aside. Written before the job moves, so that it
    never lands after the 'waiting' of a worker that claimed the job at once. Returns (the status before, the one
    written) where it wrote one, for `_unsay_queued`; else None."""
    import sys

    from spadscan.worker.live.done import mark_live_queued

    path = _live_status_path(job, root)
    before = _file_bytes(path)
    mark_live_queued(job, root, why, lambda line: print(line, file=sys.stderr), ended_too=True)
    after = _file_bytes(path)
    return None if before is None or after is None or after == before else (before, after)


def _live_status_path(job, root: Path) -> Path | None:
    """The live status file of `job`'s scan; None for a job whose scan is not inside the root (it says so itself
    when it runs)."""
    from spadscan.protocol.errors import SpadscanError
    from spadscan.protocol.live_status import status_path
    from spadscan.worker.jobs import scan_path

    try:
        return status_path(scan_path(job, root))
    except SpadscanError:
        return None


def _unsay_queued(queue, job, root: Path, said: tuple[bytes, bytes] | None) -> None:
    """Another process moved the job out of done/ before this one could queue it again: the 'queued' that
    `_say_queued` wrote (`said`) names a queuing that did not happen, and would stand for good where nothing queued
    the job. Unless the status has been written since (by the process that took the job: a worker's 'waiting'), it
    goes back to what it said before where that was the other process's 'queued', or where the job is not queued
    or running now (nothing queued it again: the earlier word stands); else (the other process queued the job
    again without saying so first) it says that the job was queued again by another process."""
    import dataclasses
    import json
    import sys

    from spadscan.protocol.atomic_files import write_atomic
    from spadscan.protocol.errors import SpadscanError
    from spadscan.protocol.live_status import read_status, write_status
    from spadscan.worker.live.done import AGAIN

    path = _live_status_path(job, root)
    if said is None or path is None:
        return
    before, ours = said
    if _file_bytes(path) != ours:
        return  # written since: the other process's word, newer than this one's
    try:
        earlier = json.loads(before)
    except ValueError:
        earlier = None
    now = queue.job_paths().get(job.id, (None, None))[0]
    try:
        if (isinstance(earlier, dict) and earlier.get("state") == "queued") or now not in ("queued", "running"):
            write_atomic(path, before)
        else:
            note = (f"queued again by another process while `spadscan worker --redo` was queuing it (that --redo "
                    f"queued nothing); {AGAIN}")
            write_status(path.parent, dataclasses.replace(read_status(path), updated_utc="", note=note))
    except (SpadscanError, OSError) as exc:
        print(f"{job.id}: the live status was not updated: {' '.join(str(exc).split())}", file=sys.stderr)


def _file_bytes(path: Path | None) -> bytes | None:
    """The bytes of file `path`, or None where there is none or it cannot be read."""
    if path is None:
        return None
    try:
        return path.read_bytes()
    except OSError:
        return None


def _jobs_in(queue, state: str, preset: str | None) -> list:
    """The readable jobs in `state` (of `preset`, if given); those whose files cannot be read are left out (the
    queue moves them all the same, and their jobs say why when they run)."""
    jobs = [queue.job_in(state, job_id) for job_id, (where, _) in sorted(queue.job_paths().items()) if where == state]
    return [job for job in jobs if job is not None and (preset is None or job.preset == preset)]


def _done_job(queue, job_id: str):
    """The done job `job_id` of `queue`; a one-line error when there is none or its job file cannot be read."""
    import json

    from spadscan.protocol.errors import ConfigError
    from spadscan.worker.jobs import Job

    state, path = queue.job_paths().get(job_id, (None, None))
    if state is None:
        raise ConfigError(f"no job {job_id} in {queue.path} (`--status` lists the jobs)")
    if state != "done":
        raise ConfigError(f"{job_id} is {state}, not done: --redo queues finished jobs again"
                          + (" (--retry-failed queues failed ones)" if state == "failed" else ""))
    try:
        return Job.from_dict(json.loads(path.read_text()), str(path))
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: cannot read the job file: {exc}") from None


def _print_status(queue, as_json: bool, root: Path) -> int:
    """List the jobs. Damaged queue files never stop the listing: each row says what its readable records say and
    names the files it could not read."""
    import json
    from dataclasses import asdict

    from spadscan.worker.job_progress import progress_field, running_progress
    from spadscan.worker.presence import present_workers, start_command, workers_line
    from spadscan.worker.status_detail import result_health, status_lines

    rows = queue.statuses()
    running = running_progress(queue, root)  # root: where a live job's status says when its final run began
    if as_json:
        print(json.dumps([{**asdict(r), **result_health(r), **progress_field(r.state, r.id, running)}
                          for r in rows], indent=1))
        return 0
    workers = workers_line(present_workers(queue.path), start_command(root, queue.path))
    if not rows:
        print(f"no jobs in {queue.path}")
        print(workers)
        return 0
    table = [("JOB", "STATE", "TRIES", "HOLDER", ["RESULT / LAST ERROR"])]
    for r in rows:
        holder = r.holder or "-"
        if r.heartbeat_age_s is not None:
            holder += f" ({r.heartbeat_age_s:.0f} s ago)"
        table.append((r.id, r.shown_state or r.state, str(r.attempts), holder, status_lines(r, running, root)))
    widths = [max(len(row[i]) for row in table) for i in range(4)]
    column = sum(widths) + 2 * len(widths)  # where the last column starts
    for row in table:
        first, *more = row[4]
        print("  ".join(cell.ljust(w) for cell, w in zip(row[:4], widths)) + "  " + first)
        for line in more:  # a done job's warnings, each on a line of its own under its row's result
            print(" " * column + line)
    counts = queue.counts()
    stale = sum(1 for r in rows if r.state == "running" and r.shown_state == "stale")
    print(", ".join(f"{n} {state}" + (f" ({stale} stale: their worker is gone)" if state == "running" and stale else "")
                    for state, n in counts.items()))
    print(workers)
    return 0
