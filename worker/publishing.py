"""Publishing a finished job's result in the order that cannot lose it, and reconciling the queue with the result
folders when a worker starts (or finds that another worker died).

The order (`publish_claim`): the job's log is copied into its scratch folder `<scan>/recon/.tmp-<job>-<token>/`, a
completion marker is written into it last (jobs.COMPLETE), the attempt record names the result folder, the folder is
renamed into place as `<scan>/recon/<job>/`, and only then is the job moved to the queue's done/. A worker killed
at any step leaves one of these states, each of which `reconcile` turns into exactly one result, or the job queued
again:

- a scratch folder without the marker: partial; its job is taken over and run again, the folder removed (once the
  dead worker's job process has exited, so that nothing writes into it again);
- a complete scratch folder of a dead claim: its claim is adopted (one rename: exactly one worker wins) and the
  result published, whether the job is still running, was queued again or failed meanwhile; a done job's complete
  scratch folder (left by a worker that marked the job done before moving its result, as earlier versions did) is
  published too;
- a result in place whose job is not done: the job is settled as done with it (`Worker` does so too when it claims a
  job whose result folder holds this queue's own result);
- a done job whose record lacks the result: the record is completed from the folder;
- a done job with no result at all (removed by hand, say): queued again, saying so.

Every path that settles a live job as done with its result sets the scan's live status to 'done' naming it
(live/done.py), as the worker that publishes its own job's result does: a worker that died while publishing must not
leave the status saying that the reconstruction is still finishing.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Callable

from spadscan.protocol.capture_format import MANIFEST
from spadscan.protocol.errors import ConfigError

from .holder import Holder
from .jobs import (RESULT_FILES, SCRATCH_RE, Job, completion, existing_result, mark_complete, move_aside, result_path,
                   scan_path, scratch_folders)
from .kill_points import kill_point
from .live.done import mark_live_done, mark_live_done_unsaid
from .queue import SEP, Claim, Queue

Log = Callable[[str], None]


def publish_claim(queue: Queue, claim: Claim, scratch: Path, final: Path,
                  log_file: Path | None = None) -> tuple[Path, Path | None] | None:
    """Publish the finished result of a held job from `scratch` to `final` and move the job to done/. Returns
    (final, the earlier folder moved aside or None), or None when the lease had been taken over (nothing changes:
    the job is another worker's now, the scratch folder the caller's to remove)."""
    kill_point("job-ended")
    if not queue.heartbeat(claim):
        return None
    if log_file is not None:
        shutil.copyfile(log_file, scratch / "job.log")
    kill_point("log-copied")
    mark_complete(scratch, claim.job.id, claim.token, queue.path)
    kill_point("marked-complete")
    return _put_in_place(queue, claim, scratch, final, "published")


def _put_in_place(queue: Queue, claim: Claim, scratch: Path, final: Path,
                  step: str) -> tuple[Path, Path | None]:
    """Rename a complete scratch folder into place, then settle the claim as done. (A lost lease at the end leaves
    the result in place: the job's next claim finds it and settles the job with it.)"""
    queue.record_result(claim, str(final))
    kill_point("result-recorded")
    aside = move_aside(final)
    kill_point("moved-aside")
    os.rename(scratch, final)
    kill_point(step)
    if queue.finish(claim, str(final)):
        kill_point("finished")
    return final, aside


def left_result(queue: Queue, claim: Claim, root: Path) -> Path | None:
    """The complete scratch folder an earlier claim of `claim`'s job left unpublished, or None: its marker names the
    job, that claim and this queue, and that claim can never publish it itself (its worker gave the job back when it
    stopped with the disk full, `Worker._leave_unpublished`, or died). The worker that claims the job next publishes
    it (`publish_left`) instead of reconstructing the job again."""
    try:
        recon = result_path(claim.job, root).parent
    except ConfigError:
        return None
    for folder in sorted(recon.glob(f".tmp-{claim.job.id}-*")):
        m = SCRATCH_RE.match(folder.name)
        if not m or m["job"] != claim.job.id or m["token"] == claim.token or not folder.is_dir():
            continue
        token = m["token"]
        if not _marked_by(folder, claim.job.id, token, queue):
            continue
        rec = queue.record(claim.job.id, token) or {}
        if rec.get("outcome") == "interrupted" or queue.claim_is_dead(claim.job.id, token):
            return folder
    return None


def publish_left(queue: Queue, claim: Claim, folder: Path, root: Path) -> tuple[Path, Path | None]:
    """Publish the result `left_result` found, under `claim` (which is then no attempt of its own: it ran nothing)."""
    token = SCRATCH_RE.match(folder.name)["token"]
    queue.note_adopted(claim, token)
    return _put_in_place(queue, claim, folder, result_path(claim.job, root), "recovered-published")


def _marked_by(folder: Path, job_id: str, token: str, queue: Queue | None = None) -> bool:
    """Whether `folder`'s completion marker says it is the whole result of claim `token` of `job_id` (in `queue`,
    when given)."""
    mark = completion(folder) or {}
    return ((mark.get("job"), mark.get("token")) == (job_id, token)
            and (queue is None or same_queue(mark.get("queue"), queue.path)))


def own_result(queue: Queue, job_id: str, folder: Path) -> dict | None:
    """The completion marker of `folder` when it holds a result this queue's claim of `job_id` produced, else None
    (a result from another queue, from a deleted queue, or from before markers existed)."""
    mark = completion(folder) if existing_result_files(folder) else None
    if not mark or mark.get("job") != job_id or not same_queue(mark.get("queue"), queue.path):
        return None
    return mark if queue.record(job_id, str(mark.get("token"))) is not None else None


def same_queue(marked, queue_path: Path) -> bool:
    """Whether a completion marker's `queue` can name the queue folder `queue_path`. Markers hold the resolved path
    (jobs.mark_complete), so workers that spell the captures root differently agree. One written by an earlier
    version may hold a path relative to its worker's working directory, unknown here: it names this queue when it
    ends with the same folders. A path that does not exist on this machine (the shared filesystem mounted elsewhere
    on the machine whose worker wrote it) is not held against the marker: its claim token, which callers look up in
    this queue's attempt records (64 random bits), says whether the result is this queue's."""
    if not isinstance(marked, str) or not marked:
        return False
    here = Path(os.path.abspath(queue_path))
    there = Path(os.path.normpath(marked))
    if not there.is_absolute():
        parts = tuple(p for p in there.parts if p not in (os.pardir, os.curdir))
        return bool(parts) and here.parts[-len(parts):] == parts
    if there == here or there.resolve() == here.resolve():
        return True
    try:
        return os.path.samefile(there, here)
    except OSError:
        return not there.exists()


def existing_result_files(folder: Path) -> bool:
    return any((Path(folder) / name).exists() for name in RESULT_FILES)


def reconcile(queue: Queue, root: Path, log: Log, *, busy: set[str] = frozenset(), startup: bool = False) -> bool:
    """Settle every disagreement between the queue and the result folders under `root` that dead workers left
    (see the module's docstring). `busy`: claim tokens this process holds. `startup`: also check every done job
    for its result. Returns True when something must wait for a later pass (a dead claim's job process is still
    running)."""
    pending = _scratch_folders(queue, root, log, busy)
    _results_in_place(queue, root, log, busy)
    if startup:
        _done_jobs(queue, root, log)
    return pending


def _scratch_folders(queue: Queue, root: Path, log: Log, busy) -> bool:
    pending = False
    for folder, job_id, token in scratch_folders(root):
        if token in busy or not queue.claim_is_dead(job_id, token):
            continue  # a live claim's, or no claim of this queue's
        state, path = queue.job_paths().get(job_id, (None, None))
        if state == "running" and _adopted_by_live_claim(queue, job_id, path, token):
            continue  # being published by the worker that adopted it
        if _publishable(queue, folder, job_id, token, state, path):
            _publish_left(queue, root, folder, job_id, token, state, path, log)
        elif _marked_by(folder, job_id, token):
            _finished_elsewhere(queue, root, folder, job_id, state, path, log)
        elif not queue.job_process_gone(job_id, token):
            pending = True  # its orphaned job process is still exiting: it could write into the folder again
        else:
            shutil.rmtree(folder, ignore_errors=True)
            log(f"removed the partial result {folder} of a dead worker")
    return pending


def _publishable(queue: Queue, folder: Path, job_id: str, token: str, state: str | None, path: Path | None) -> bool:
    """Whether the scratch folder of dead claim `token` holds the job's result, to be published rather than removed:
    complete (its marker names this claim) while the job is not done or running under another claim; or, the job
    being done by this very claim, holding a result (an earlier version's worker died between the two). Running
    under a dead claim includes one that adopted this folder and died too."""
    if state == "done":
        rec = queue.record(job_id, token) or {}
        return rec.get("outcome") == "done" and existing_result_files(folder)
    mark = completion(folder)
    if not mark or (mark.get("job"), mark.get("token")) != (job_id, token):
        return False
    return state in ("queued", "failed") or (state == "running"
                                             and queue.claim_is_dead(job_id, path.stem.rpartition(SEP)[2]))


def _finished_elsewhere(queue: Queue, root: Path, folder: Path, job_id: str, state: str | None, path: Path | None,
                        log: Log) -> None:
    """A whole result of a dead claim that is not to be published now. While its job is held by a live claim, the
    folder stays: that claim's worker publishes it (`left_result`, when it claimed the job). Once the job is done with
    a result in place, this one is a second result of it, removed as such (never called partial)."""
    if state != "done":
        return
    job = _job(path)
    final = existing_result(job, root) if job is not None else None
    if final is None:
        return  # _done_jobs queues the job again; this folder may yet be its result
    shutil.rmtree(folder, ignore_errors=True)
    log(f"{job_id}: removed {folder}, a finished result a stopped worker could not publish: the job was done since "
        f"with the result in {final}")


def _adopted_by_live_claim(queue: Queue, job_id: str, path: Path, token: str) -> bool:
    held = path.stem.rpartition(SEP)[2]
    return (queue.record(job_id, held) or {}).get("adopted") == token and not queue.claim_is_dead(job_id, held)


def _publish_left(queue: Queue, root: Path, folder: Path, job_id: str, token: str, state: str, path: Path,
                  log: Log) -> None:
    dead = _holder_of(queue, job_id, token)
    if state == "done":  # the job is already settled: only its result is missing from its place
        job = _job(path)
        if job is None:
            return
        final = result_path(job, root)
        aside = None
        try:
            os.rename(folder, final)  # fails if another worker published it first, or a result is in the way
        except FileNotFoundError:
            return
        except OSError:
            aside = move_aside(final)
            os.rename(folder, final)
        kill_point("recovered-published")
        queue.record_done(job_id, str(final))
        log(f"{job_id}: published the finished result {dead} left in {folder.name} -> {final}"
            + (f" (moved {aside} aside)" if aside else ""))
        _live_done(job, root, final, log)
        return
    claim = queue.adopt(job_id, path, token, why=f"{dead} died after finishing the job; its result was published "
                                                 f"by worker {_me()}")
    if claim is None:
        return  # another worker adopted it, or the job moved on
    final = result_path(claim.job, root)
    _put_in_place(queue, claim, folder, final, "recovered-published")
    log(f"{job_id}: published the finished result {dead} left in {folder.name} -> {final}")
    _live_done(claim.job, root, final, log)


def _live_done(job: Job, root: Path, final: Path, log: Log) -> None:
    """A live job settled as done with its result `final`: its live status says so (live.done.mark_live_done)."""
    if job.live:
        mark_live_done(job, root, final, log)


def _results_in_place(queue: Queue, root: Path, log: Log, busy) -> None:
    """Jobs not done (running under a dead claim, or queued again, or failed meanwhile) whose result folder holds
    the result one of their claims published: settled as done with it."""
    for job_id, (state, path) in queue.job_paths().items():
        if state not in ("running", "failed"):
            continue  # a queued job with its result in place is settled when it is claimed (Worker._start)
        if state == "running":
            token = path.stem.rpartition(SEP)[2]
            if token in busy or not queue.claim_is_dead(job_id, token):
                continue
        job = _job(path)
        if job is None:
            continue
        try:
            final = result_path(job, root)
        except ConfigError:
            continue
        mark = own_result(queue, job_id, final)
        if mark is None:
            continue
        dead = str(mark["token"])
        claim = queue.adopt(job_id, path, dead, why=f"{_holder_of(queue, job_id, dead)} died after publishing the "
                                                    f"result; worker {_me()} recorded the job as done")
        if claim is not None and queue.finish(claim, str(final)):
            log(f"{job_id}: its result {final} was in place, the job {state}: recorded it as done")
            _live_done(job, root, final, log)


def _done_jobs(queue: Queue, root: Path, log: Log) -> None:
    """Every done job has its result: a record that lacks it is completed; a job whose result is gone while its scan
    is still there is queued again (a scan moved out of the root, archived, leaves its job done)."""
    for job_id, (state, path) in sorted(queue.job_paths().items()):
        if state != "done":
            continue
        job = _job(path)
        if job is None:
            continue
        final = existing_result(job, root)
        if final is not None:
            queue.record_done(job_id, str(final))
            if job.live and own_result(queue, job_id, final) is not None:
                # Its worker died between moving the job to done/ and saying so in the live status (a kept result,
                # which the job did not make, is not its live run's).
                mark_live_done_unsaid(job, root, final, log)
            continue
        try:
            where = result_path(job, root)
            if not (scan_path(job, root) / MANIFEST).is_file():
                continue  # the whole scan was moved away (archived) or deleted: nothing to make again
        except ConfigError as exc:
            where = f"its scan ({exc})"
        if queue.requeue("done", job_id):
            log(f"{job_id}: done, but its result {where} is missing: queued again")


def _job(path: Path) -> Job | None:
    try:
        return Job.from_dict(json.loads(Path(path).read_text()), str(path))
    except (OSError, ValueError, ConfigError):
        return None


def _holder_of(queue: Queue, job_id: str, token: str) -> str:
    rec = queue.record(job_id, token) or {}
    return f"worker {rec.get('host', '?')} pid {rec.get('pid', '?')}"


def _me() -> str:
    h = Holder.current()
    return f"{h.host} pid {h.pid}"
