"""What a job is and what running one means: check the capture, reconstruct it, publish the results under the scan.

A job's results land in `<scan>/recon/<job id>/` (mesh.ply, report.json, pictures, job.json). They are written into
a hidden temporary folder beside it and published by one rename, so a reader never sees half a result; every path
a result records (the ground truth it was scored against, say) is the one it has once published. A result is never
replaced in silence: the worker does not run a job whose folder already holds one (it records the job as done), and
`publish` moves an earlier folder aside instead of deleting it.

`python -m spadscan.worker.jobs` is the child process the worker pool starts for each job: it runs one job into the
folder the pool names and writes an outcome file the pool reads (exit 0 done, 3 the input is at fault and a retry
would fail the same way, 4 the job crashed, 5 it met a full disk: no fault of the job's, which the pool gives back
to the queue without counting the attempt; said by the exit status alone where the outcome file does not fit, and a
job that finished but whose outcome file does not fit exits 6: its result is whole, published, not reconstructed
again).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import hashlib
import importlib
import json
import math
import numbers
import os
import re
import secrets
import shlex
import shutil
import sys
import threading
import time
import traceback
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Callable

from spadscan.protocol.atomic_files import write_atomic
from spadscan.protocol.capture_format import MANIFEST
from spadscan.protocol.capture_writer import file_size_limit
from spadscan.protocol.disk_full import disk_full_cause
from spadscan.protocol.errors import CaptureError, ConfigError, SpadscanError

from .budget import process_started
from .disk_room import full_folder
from .outputs import RESULT_FILES
from .publish_out import move_aside

ID_RE = re.compile(r"[^A-Za-z0-9._-]+")
RECON_DIR = "recon"
DEFAULT_QUEUE = ".queue"
"""The name of a root's own queue folder (queue.QUEUE_DIRNAME: defined here, where the command that names a queue is
built, since the queue module imports this one)."""
EXIT_DONE, EXIT_INPUT, EXIT_CRASH, EXIT_FULL, EXIT_DONE_UNSAID = 0, 3, 4, 5, 6
"""EXIT_DONE_UNSAID: the job finished, its result whole in its folder, but its outcome file met a full disk (the
queue's): the pool publishes the result (its summary read from its report.json, `summary_of`)."""
SUMMARY_KEYS = ("chamfer_mm", "seconds", "steps", "ground_truth_note", "capture_counts_note", "converged", "warnings")
"""What of a finished job's report its outcome file carries to the pool's done line."""

ReconFn = Callable[..., dict]
"""`reconstruct_capture(capture, out, *, preset, budget_s, steps, gt, device, seed, started) -> report dict`:
`budget_s` counts from `started` (a time.perf_counter reading: the job process's start)."""


MAX_ID = 200
"""Longest job id: it names files and folders with up to 31 more characters (`<id>.replaced-<time>-<hex>`)."""


def job_id_for(scan_name: str, preset: str, *, hashed: bool = False) -> str:
    """Deterministic job id of one scan and preset, made of the characters [A-Za-z0-9._-], and no other scan's.

    `<scan>-<preset>` when that is such a name (of at most MAX_ID characters, not starting with a dot); otherwise,
    or with `hashed`, `<scan with every run of other characters replaced by _>-<8 hex digits>-<preset>`, the digits
    from a hash of `<scan>-<preset>`: replacing characters alone would give `x+y` and `x_y` (or `mug 1` and `mug_1`)
    one id, and the queue queues an id once, so one of the two scans would never be reconstructed. `hashed` gives a
    scan whose plain id another scan's job already holds (in a queue of an older spadscan: `old_job_id_for`) an id
    of its own."""
    plain = f"{scan_name}-{preset}"
    if not hashed and not ID_RE.search(plain) and not plain.startswith(".") and len(plain) <= MAX_ID:
        return plain  # the ids every queue has always held for such names: existing queues keep their jobs
    # surrogateescape: a folder name need not be UTF-8 (os.listdir gives its bytes as surrogates)
    digest = hashlib.sha256(plain.encode("utf-8", "surrogateescape")).hexdigest()[:8]
    tail = f"-{digest}-{ID_RE.sub('_', preset)}"
    return ID_RE.sub("_", scan_name).lstrip(".")[:MAX_ID - len(tail)] + tail


def old_job_id_for(scan_name: str, preset: str) -> str:
    """The id spadscan gave a scan's job before ids were made one scan's each (every run of characters outside
    [A-Za-z0-9._-] replaced by `_`, cut to MAX_ID characters): the watcher looks a scan up under it too, so that a
    queue written then does not run its jobs again under their new ids."""
    return (ID_RE.sub("_", f"{scan_name}-{preset}").strip(".") or "job")[:MAX_ID]


CHANGEABLE = ("budget_s", "steps", "device", "seed")
"""Options a failed job may be queued again with (Queue.retry_failed); its preset is part of its id, so it stays."""


@dataclass(frozen=True)
class Job:
    """What to reconstruct and how. Stored as the job file when queued; only `spadscan worker --retry-failed`
    with options given queues it again with those options changed (a new job file)."""

    id: str
    """Deterministic id (see `job_id_for`)."""
    scan: str
    """Scan folder relative to the captures root."""
    preset: str = "fast"
    """Reconstruction preset."""
    budget_s: float | None = None
    """Wall-clock budget of the reconstruction (seconds); None = the preset's default."""
    steps: int | None = None
    """Optimisation steps; None = the preset's default."""
    device: str = "auto"
    """'auto', 'cpu' or 'cuda'."""
    seed: int = 0
    """Random seed of the reconstruction, 0 to MAX_SEED."""
    created_utc: str = ""
    live: bool = False
    """Reconstruct while the scan is recorded (`spadscan worker --live`): the job starts at the scan's first chunk,
    follows it and finishes from the live state (`worker/live/job.py`); `budget_s` then bounds that final run."""
    owner: str = ""
    """A live job's token, random, given when it is queued (`Queue.enqueue`) and kept by its retries and its
    --redo: its live status carries it (`LiveStatus.owner`). Two queues on one root queue a scan's live job under
    one id; the token tells the one that holds the scan's live folder from the other (`worker.live.done.holds`).
    Empty: a job queued by an earlier version, known by its id alone."""

    def to_dict(self) -> dict:
        data = asdict(self)
        if not self.live:
            del data["live"]  # an ordinary job's file is as it always was
        if not self.owner:
            del data["owner"]
        return data

    @classmethod
    def from_dict(cls, data: dict, where: str = "job") -> "Job":
        names = {f.name for f in fields(cls)}
        if not isinstance(data, dict) or not {"id", "scan"} <= set(data):
            raise ConfigError(f"{where}: not a job record (needs 'id' and 'scan')")
        for key, value in data.items():  # a file written by another tool: every field of the type it must have
            if key in FIELD_TYPES and not _has_type(value, FIELD_TYPES[key]):
                raise ConfigError(f"{where}: {key} = {json.dumps(value)[:60]} is not {FIELD_TYPES[key][1]}")
        return cls(**{k: v for k, v in data.items() if k in names})


MAX_SEED = 2**63 - 1
"""The largest seed a reconstruction takes: torch's generators take a signed 64-bit integer."""
MAX_BUDGET_S = 7 * 24 * 3600.0
"""The longest time budget a reconstruction takes, s (a week): a larger one is a slip of the keyboard, not a plan."""
MAX_STEPS = 10_000_000
"""The most optimisation steps a reconstruction takes: about a week of the fast preset on a CPU."""


LIMIT_FLAGS = {"budget_s": "--budget-s", "steps": "--steps", "seed": "--seed"}
"""The command-line flag of each run limit, as `spadscan reconstruct`, `worker` and `demo` name them."""


def run_limits_problem(budget_s, steps, seed, flags: bool = False) -> str | None:
    """Why a reconstruction cannot run with this time budget (s, or None: the preset's), steps (or None) and seed,
    in one line; None when it can. One rule for `spadscan reconstruct`, the worker's options and its jobs, and the
    demo. `flags`: the line starts with the flag of the value at fault ("--budget-s: ..."), for a command's
    options; a job's own values have no flag. A budget of 1e309 is infinite once read as a float, so it is not
    shown as "inf", which the user never typed."""
    problem = _limits_problem(budget_s, steps, seed)
    if problem is None:
        return None
    key, line = problem
    return f"{LIMIT_FLAGS[key]}: {line}" if flags else line


def _limits_problem(budget_s, steps, seed) -> tuple[str, str] | None:
    """(the run limit at fault, a key of LIMIT_FLAGS; why, in one line), or None."""
    budget_rule = f"> 0 and at most {MAX_BUDGET_S:.0f} (a week)"
    if budget_s is not None and _is_number(budget_s) and not math.isfinite(budget_s):
        return "budget_s", f"time budget is not a finite number of seconds: it must be {budget_rule}"
    if budget_s is not None and not (_is_number(budget_s) and 0 < budget_s <= MAX_BUDGET_S):
        return "budget_s", f"time budget {budget_s} s must be a number of seconds {budget_rule}"
    if steps is not None and not (_is_int(steps) and 1 <= steps <= MAX_STEPS):
        return "steps", f"steps {steps} must be an integer in [1, {MAX_STEPS:,}]"
    if not (_is_int(seed) and 0 <= seed <= MAX_SEED):
        return "seed", f"seed {seed} must be an integer in [0, {MAX_SEED}]"
    return None


def _is_int(v) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


FIELD_TYPES = {"id": ("str", "a string"), "scan": ("str", "a string"), "preset": ("str", "a string"),
               "device": ("str", "a string"), "created_utc": ("str", "a string"),
               "budget_s": ("number?", "a number or null"), "steps": ("int?", "an integer or null"),
               "seed": ("int", "an integer"), "live": ("bool", "true or false"), "owner": ("str", "a string")}
"""What each field of a job file must hold (kind, and how an error names it)."""


def _has_type(value, kind: tuple[str, str]) -> bool:
    name = kind[0].rstrip("?")
    if value is None:
        return kind[0].endswith("?")
    if name == "bool":
        return isinstance(value, bool)
    if isinstance(value, bool):
        return False
    return isinstance(value, {"str": str, "int": int, "number": (int, float)}[name])


def load_recon(spec: str | None = None) -> ReconFn:
    """The reconstruction function: `spadscan.worker.reconstruct.reconstruct_capture`, or `module:function`."""
    if spec is None:
        from spadscan.worker.reconstruct import reconstruct_capture  # torch: imported only in the job's process

        return reconstruct_capture
    module, _, name = spec.partition(":")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"cannot load reconstruction function {spec!r}: {exc}") from None


def scan_path(job: Job, root: Path) -> Path:
    """The job's scan folder; refuses paths that leave the captures root."""
    root = Path(root).resolve()
    path = (root / job.scan).resolve()
    if root not in path.parents:
        raise ConfigError(f"job {job.id}: scan {job.scan!r} is not inside the captures root {root}")
    return path


def scan_state(job: Job, root: Path) -> str | None:
    """The state the job's scan records (its scan.json's: 'running', 'complete', 'aborted'), or None where that
    cannot be read (no manifest, a damaged one, a scan outside the captures root)."""
    try:
        return json.loads((scan_path(job, root) / MANIFEST).read_text()).get("state")
    except (OSError, ValueError, AttributeError, ConfigError):
        return None


def check_capture(scan: Path) -> tuple[dict, str | None]:
    """Validate a capture before reconstructing it: manifest, state 'complete', every chunk readable, counts a
    sensor could have produced.

    Returns (the manifest, a one-line warning about some of its counts or None). Raises CaptureError with the
    one-line reason otherwise.
    """
    from spadscan.protocol.capture_reader import CaptureReader

    reader = CaptureReader(scan)
    if reader.state != "complete":
        raise CaptureError(f"{scan}: scan state is {reader.state!r}, not 'complete'")
    data = reader.load()  # reads and checks every chunk: shapes, dtypes, finite rigid poses
    if len(data.hists) == 0:
        raise CaptureError(f"{scan}: holds no measurements")
    return reader.manifest, data.check_counts(scan)


def ground_truth(manifest: dict, out: Path) -> tuple[Path | None, str | None]:
    """(a usable ground-truth mesh file for the capture, or None; why there is none although the manifest names one).

    See `ground_truth.named_ground_truth`; a built-in scene, or any scene the capture placed with `mesh_offset_m`, is
    exported into `out` (ground_truth.ply) as it stood, so that the job's results hold what they were scored
    against."""
    from spadscan.protocol.mesh_io import BUILTIN_PREFIX

    from .ground_truth import named_ground_truth, scene_offset_m

    spec, note = named_ground_truth(manifest)
    offset = scene_offset_m(manifest)
    if spec is None or (offset is None and not spec.startswith(BUILTIN_PREFIX)):
        return (None if spec is None else Path(spec)), note
    return _export_placed(spec, offset, out / "ground_truth.ply")


def _export_placed(spec: str, offset, path: Path) -> tuple[Path | None, str | None]:
    """(`path`, None) once the mesh `spec` (a file or builtin:NAME), moved by `offset` (metres) when not None, is
    written there as the scene stood when scanned; else (None, why)."""
    try:
        from spadscan.protocol.mesh_io import load_mesh_spec

        mesh = load_mesh_spec(spec)[0]  # a new mesh each time: moving it moves no one else's
        if offset is not None:
            mesh.apply_translation(offset)
        mesh.export(path)
        return path, None
    except (ImportError, OSError, SpadscanError) as exc:
        with contextlib.suppress(OSError):  # a file cut short (a size limit) would read as a ground truth
            path.unlink(missing_ok=True)
        moved = "" if offset is None else f" moved by {list(offset)}"
        return None, f"{spec}{moved}: {exc}; no metrics"


def execute_job(job: Job, root: Path, out: Path, recon: ReconFn | None = None, *,
                started: float | None = None, queue: Path | None = None) -> dict:
    """Reconstruct the job's capture into the folder `out` (created), to be published as `result_path(job, root)`:
    paths into `out` that the results record (job.json, report.json, report.html) name the published folder. Returns
    the reconstruction's report, with `ground_truth_note` when the capture names a ground truth that cannot be used
    and `capture_counts_note` when some of its histograms are implausible (both also added to report.json).

    The job's time budget bounds the whole job from `started` (a time.perf_counter reading; default: now): the
    reconstruction counts it from there, so what checking the capture, loading torch and placing the ground truth
    took is part of it, and its report's times are the job's (report.json: `job_budget_s`). A live job (`job.live`)
    follows its scan first (worker/live/job.py); its final run is an ordinary job, its budget counted from the scan's
    end. `queue`: the queue the job was claimed from (None: the root's own), which the command job.json records to
    run the job again (`redo_command`) names."""
    if job.live:
        from .live.job import execute_live_job

        return execute_live_job(job, root, out, recon, queue=queue)
    started = time.perf_counter() if started is None else started
    scan = scan_path(job, root)
    manifest, counts_note = check_capture(scan)
    if counts_note:
        print(f"warning: {counts_note}", file=sys.stderr, flush=True)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    final = result_path(job, root)
    gt, gt_note = ground_truth(manifest, out)
    (out / "job.json").write_text(json.dumps({**job.to_dict(), "capture": str(scan),
                                              "gt": None if gt is None else str(published_path(gt, out, final)),
                                              "gt_note": gt_note, "redo": redo_command(job, root, queue)},
                                             indent=1) + "\n")
    if gt_note:
        print(f"ground truth: {gt_note}", file=sys.stderr, flush=True)
    recon = recon or load_recon()
    report = dict(recon(scan, out, preset=job.preset, budget_s=job.budget_s, steps=job.steps, gt=gt,
                        device=job.device, seed=job.seed, started=started) or {})
    moved = {k: str(published_path(Path(v), out, final)) for k, v in report.items()
             if isinstance(v, str) and Path(v).is_relative_to(out)}
    extra = {**moved, **({"ground_truth_note": gt_note} if gt_note else {}),
             **({"capture_counts_note": counts_note} if counts_note else {}),
             **({"job_budget_s": job.budget_s} if job.budget_s is not None else {})}
    if extra:
        report.update(extra)
        add_to_report(out, extra)
    return report


def redo_command(job: Job, root: Path, queue: Path | None = None) -> str:
    """The command that moves the job's result aside and queues the job again, then exits: a worker on that root and
    queue (a running one, or one started with --once) then reconstructs it. Recorded as job.json's `redo`, which a
    result's report names where a part of it could not be written. `queue`: the worker's queue (None: the root's
    own)."""
    return worker_command(root, queue, "--redo", job.id)


def worker_command(root: Path, queue: Path | None, *words: str) -> str:
    """`spadscan worker --root ROOT [--queue QUEUE] WORDS...` as a shell reads it, each word quoted where it must be.
    Root and queue are absolute (a report is read, and its command run, from anywhere); --queue only when `queue` is
    not the root's own queue, which the command finds by itself."""
    root = Path(root).resolve()
    command = ["spadscan", "worker", "--root", str(root)]
    if queue is not None and Path(queue).resolve() != (root / DEFAULT_QUEUE).resolve():
        command += ["--queue", str(Path(queue).resolve())]
    return shlex.join([*command, *words])


def published_path(path: Path, scratch: Path, final: Path) -> Path:
    """Where `path`, inside the scratch folder a job writes into, will be once that folder is published as `final`
    (other paths are returned unchanged)."""
    path = Path(path)
    return final / path.relative_to(scratch) if path.is_relative_to(scratch) else path


def add_to_report(out: Path, values: dict) -> None:
    """Add `values` to the report.json the reconstruction wrote into `out` (and to its report.html page)."""
    from spadscan.worker.report.report_html import REPORT_HTML, write_report_html
    from spadscan.worker.report.report_json import REPORT, write_report

    try:
        report = json.loads((out / REPORT).read_text())
    except (OSError, ValueError):
        return  # no report to add to (a replacement reconstruction may write none)
    if not isinstance(report, dict):
        return
    report.update(values)
    write_report(out, report)
    if (out / REPORT_HTML).exists():
        write_report_html(report, out)


def result_path(job: Job, root: Path) -> Path:
    """Where the job's results are published: `<scan>/recon/<job id>/`."""
    return scan_path(job, root) / RECON_DIR / job.id


SCRATCH_RE = re.compile(r"^\.tmp-(?P<job>.+)-(?P<token>[0-9a-f]{16})$")
"""Name of a queued claim's scratch folder: `.tmp-<job id>-<claim token>` (the token says whose it is)."""


def scratch_path(job: Job, root: Path, token: str | None = None) -> Path:
    """A fresh hidden folder beside the result folder to write one attempt's results into.

    `token`: the queue claim's token, so that a scratch folder left by a dead worker can be told from one in use
    (see SCRATCH_RE); without it (a job run outside the queue) a shorter random suffix that no sweep touches."""
    return scan_path(job, root) / RECON_DIR / f".tmp-{job.id}-{token or secrets.token_hex(4)}"


def scratch_folders(root: Path) -> list[tuple[Path, str, str]]:
    """(folder, job id, claim token) of every queued claim's scratch folder under the scans of `root`."""
    found = []
    for path in sorted(Path(root).glob(f"*/{RECON_DIR}/.tmp-*")):
        m = SCRATCH_RE.match(path.name)
        if m and path.is_dir():
            found.append((path, m["job"], m["token"]))
    return found


COMPLETE = ".complete"
"""Marker written last into a job's scratch folder, once everything else is in it (report, mesh, pictures, job.log):
{"job": id, "token": claim token, "queue": the queue folder's resolved path}. A scratch folder without it may be
partial; a result folder with it names the claim that produced it. The path is resolved so that workers that spell
the captures root differently (relative to their working directories, or absolute) agree on whose result it is
(publishing.same_queue)."""


def mark_complete(folder: Path, job_id: str, token: str, queue: Path) -> None:
    """Write the completion marker into `folder` (a temporary file renamed into place, fsynced with the folder),
    after every file already there is on disk: the marker says the result is whole, and after a power cut it must
    not outlive a mesh that was still in the page cache."""
    folder = Path(folder)
    _sync_tree(folder)
    tmp = folder / f"{COMPLETE}.tmp"
    with open(tmp, "w") as f:
        json.dump({"job": job_id, "token": token, "queue": str(Path(queue).resolve())}, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, folder / COMPLETE)
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _sync_tree(folder: Path) -> None:
    """fsync every file and folder under `folder` (links are not followed)."""
    for path in sorted(folder.rglob("*")):
        if path.is_symlink() or not (path.is_file() or path.is_dir()):
            continue
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def completion(folder: Path) -> dict | None:
    """The completion marker of a scratch or result folder, or None when there is none (or it is unreadable)."""
    try:
        data = json.loads((Path(folder) / COMPLETE).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def existing_result(job: Job, root: Path) -> Path | None:
    """`<scan>/recon/<job id>/` when it already holds a result (outputs.RESULT_FILES), else None."""
    try:
        final = result_path(job, root)
    except ConfigError:
        return None  # a scan outside the root: the job fails later, saying so
    return final if any((final / name).exists() for name in RESULT_FILES) else None


def publish(scratch: Path, final: Path) -> tuple[Path, Path | None]:
    """Move a finished scratch folder into place by rename. An earlier folder of the same job is never deleted: it
    is renamed aside to `<job id>.replaced-<UTC time>-<4 hex digits>` first. Returns (final, the earlier folder's new
    path or None)."""
    aside = move_aside(final)
    os.rename(scratch, final)
    return final, aside


def run_job(job: Job, root: Path, *, recon: ReconFn | None = None) -> Path:
    """Run one job in this process and publish its results; returns `<scan>/recon/<job id>/` (an earlier result
    there is moved aside, see `publish`)."""
    scratch = scratch_path(job, root)
    try:
        execute_job(job, root, scratch, recon)
        return publish(scratch, result_path(job, root))[0]
    finally:
        if scratch.exists():
            shutil.rmtree(scratch, ignore_errors=True)


# ---- the job's child process -----------------------------------------------------------------------------------
def _exit_with_parent(parent: int | None = None, poll_s: float = 0.5) -> None:
    """End this process when the worker that started it dies (its lease then expires and another worker retries).

    `parent`: the worker's pid, passed on the command line. Taking it from os.getppid() at start-up would miss a
    worker that died before this process got that far: the orphan's parent is then already init (or a subreaper),
    and it would run its whole reconstruction for nobody. So a job whose parent is not the worker exits at once."""
    parent = os.getppid() if parent is None else parent
    if os.getppid() != parent:
        os._exit(EXIT_CRASH)

    def watch():
        while True:
            time.sleep(poll_s)
            if os.getppid() != parent:
                os._exit(EXIT_CRASH)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _write_outcome(path: Path, data: dict) -> None:
    write_atomic(path, json.dumps(data) + "\n")


def _say(line: str) -> None:
    """A line in the job's log (its stderr), which a full disk may keep out: the outcome and the exit status say what
    matters."""
    try:
        print(line, file=sys.stderr, flush=True)
    except OSError:
        pass


def _ended(outcome: Path, data: dict, code: int, unsaid: int = EXIT_FULL) -> int:
    """Write the outcome file and return the exit status `code`; `unsaid` when a full disk keeps the file out (the
    exit status alone then tells the pool: EXIT_FULL for a job that ended in error, the job not at fault; a job that
    finished passes EXIT_DONE_UNSAID, and its whole result is published)."""
    try:
        _write_outcome(outcome, data)
    except OSError as exc:
        if disk_full_cause(exc) is None:
            raise
        return unsaid
    return code


def summary_of(report: dict) -> dict:
    """What of a finished job's report its done line says (SUMMARY_KEYS)."""
    return {k: report[k] for k in SUMMARY_KEYS if k in report}


def _ended_in_error(exc: Exception, outcome: Path, out: Path) -> int:
    """Say how the job ended in error and return its exit status: the disk was full (EXIT_FULL, one line naming the
    folder: no traceback, nothing in the job is at fault), its input is at fault (EXIT_INPUT), or it crashed
    (EXIT_CRASH, with the traceback). A full disk's folder is the one its error names, else the one of the job's
    result folder and the queue's (where its outcome and log go) whose filesystem has the least room
    (`disk_room.full_folder`); a full quota (EDQUOT) says so (`quota`): free space does not show it."""
    full = disk_full_cause(exc)
    if full is not None:
        folder = full_folder(full, [out, outcome.parent])
        why = full.strerror or str(full)
        quota = full.errno == errno.EDQUOT
        _say(f"job stopped: no room left {'in the disk quota' if quota else 'on the disk'}: {folder} could not be "
             f"written ({why})")
        return _ended(outcome, {"ok": False, "kind": "full", "error": why, "folder": str(folder), "quota": quota},
                      EXIT_FULL)
    if isinstance(exc, OSError) and exc.errno == errno.EFBIG:
        # Not a full disk, nor a bug: this process may not write a file that large, and another attempt may not
        # either. Failed, with the limit named, not a crash retried to the end of its attempts.
        limit = file_size_limit()
        where = exc.filename or f"a file in {out}"
        said = f"this process may write files of at most {limit:,} bytes" if limit is not None else "a size limit"
        error = f"file too large: {where} could not be written ({said}: raise `ulimit -f` for the worker)"
        _say(f"job failed: {error}")
        return _ended(outcome, {"ok": False, "kind": "input", "error": error}, EXIT_INPUT)
    if isinstance(exc, SpadscanError):
        _say(f"job failed: {exc}")
        return _ended(outcome, {"ok": False, "kind": "input", "error": str(exc)}, EXIT_INPUT)
    try:
        traceback.print_exc()
    except OSError:
        pass
    return _ended(outcome, {"ok": False, "kind": "crash", "error": f"{type(exc).__name__}: {exc}"}, EXIT_CRASH)


def child_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m spadscan.worker.jobs", description="Run one queued job.")
    parser.add_argument("--job", required=True, help="the job record as JSON")
    parser.add_argument("--root", required=True, help="captures root")
    parser.add_argument("--out", required=True, help="folder to write the results into")
    parser.add_argument("--outcome", required=True, help="file to write the outcome into (JSON)")
    parser.add_argument("--queue", default=None,
                        help="the queue the job was claimed from (default: ROOT/.queue), named by the command the "
                             "result records to run the job again")
    parser.add_argument("--parent-pid", type=int, default=None,
                        help="pid of the worker that started this job: the job ends when that process does")
    parser.add_argument("--recon", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    _exit_with_parent(args.parent_pid)
    outcome = Path(args.outcome)
    t0 = time.monotonic()
    started = process_started()  # the job's budget counts from its process's start
    try:
        job = Job.from_dict(json.loads(args.job))
        report = execute_job(job, Path(args.root), Path(args.out), load_recon(args.recon), started=started,
                             queue=Path(args.queue) if args.queue else None)
    except Exception as exc:  # bad input, a full disk, a bug or another resource problem: see _ended_in_error
        return _ended_in_error(exc, outcome, Path(args.out))
    return _ended(outcome, {"ok": True, "seconds": round(time.monotonic() - t0, 3), "summary": summary_of(report)},
                  EXIT_DONE, unsaid=EXIT_DONE_UNSAID)


if __name__ == "__main__":
    sys.exit(child_main())
