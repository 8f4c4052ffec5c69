"""Watching a captures root: every complete scan is queued once (asyncio polling, no extra dependency).

A scan folder is a child of the root that holds `scan.json`. Scans still `running` are looked at again on the next
poll; `aborted` scans are skipped; a `complete` scan is queued as the job `<scan>-<preset>` (`job_id_for`: a name
with other characters than [A-Za-z0-9._-] gets a hash of its own in its id). With `live` a `running`
scan is queued as soon as its first chunk is published, as a live job of the same id (`Job.live`): it follows the
scan and finishes it (worker/live/job.py), so the scan is still queued once. A scan whose manifest
cannot be read is queued too, so that its job fails with the reason and `spadscan worker --status` shows it, instead
of the scan being ignored in silence; but a folder that may be a copy still under way (a manifest that cannot be
read, or a complete one whose chunks lack measurements, changed within `SETTLE_S`) is looked at again first. Job ids
are deterministic, so polling again (or another worker polling the same root) never queues a scan twice.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

from spadscan.protocol.capture_format import MANIFEST, chunk_index, npy_is_whole, read_json
from spadscan.protocol.errors import CaptureError, ConfigError, SpadscanError

from .jobs import Job, job_id_for, old_job_id_for, run_limits_problem
from .queue import QUEUE_DIRNAME, Queue


DEVICES = ("auto", "cpu", "cuda")


@dataclass(frozen=True)
class JobOptions:
    """How every scan found by the watcher is reconstructed. Each job keeps the options it was queued with."""

    preset: str = "fast"
    budget_s: float | None = None
    """Wall-clock budget per reconstruction (seconds); None = the preset's."""
    steps: int | None = None
    """Optimisation steps per reconstruction; None = the preset's."""
    device: str = "auto"
    seed: int = 0
    live: bool = False
    """Queue a scan as a live job as soon as its first chunk is published (else once it is complete)."""

    def check(self) -> "JobOptions":
        """Refuse options every job would fail on, before any job is queued with them."""
        from spadscan.worker.recon.config import PRESET_NAMES  # plain dataclasses: no torch here

        if self.preset not in PRESET_NAMES:
            raise ConfigError(f"unknown preset {self.preset!r} (known: {', '.join(PRESET_NAMES)})")
        problem = run_limits_problem(self.budget_s, self.steps, self.seed)
        if problem:
            raise ConfigError(problem)
        check_device(self.device)
        if self.live and self.preset != LIVE_PRESET:
            raise ConfigError(f"live reconstruction runs the {LIVE_PRESET!r} preset, not {self.preset!r} (leave out "
                              f"--live, or --preset)")
        return self

    def job_for(self, scan_name: str, live: bool = False) -> Job:
        """The job of scan `scan_name`; `live`: a live job (the scan is still being recorded)."""
        return Job(id=job_id_for(scan_name, self.preset), scan=scan_name, preset=self.preset,
                   budget_s=self.budget_s, steps=self.steps, device=self.device, seed=self.seed, live=live)


LIVE_PRESET = "fast"
"""The preset a live job can run: its model grows with the views (`FastModel.warm_start`)."""


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def check_device(device: str) -> str:
    """`device` when jobs can run on it: 'auto', 'cpu', or 'cuda' where torch sees a CUDA device."""
    if device not in DEVICES:
        raise ConfigError(f"device {device!r} must be one of {', '.join(DEVICES)}")
    if device == "cuda":
        try:
            import torch  # only for 'cuda': the worker process itself otherwise never loads torch
        except ImportError:
            raise ConfigError("device 'cuda' asked for, but torch is not installed") from None
        if not torch.cuda.is_available():
            raise ConfigError("device 'cuda' asked for, but torch sees no CUDA device (use --device cpu or auto)")
    return device


@dataclass
class ScanReport:
    """What one pass over the root found. Lists hold scan folder names."""

    queued: list[str] = field(default_factory=list)
    live: list[str] = field(default_factory=list)
    """Scans still being recorded, queued as live jobs."""
    pending: list[str] = field(default_factory=list)
    """Scans still being recorded, or still being copied in (`SETTLE_S`)."""
    settling: dict[str, float] = field(default_factory=dict)
    """Those of `pending` taken for a copy still under way -> seconds until they are queued if nothing in them
    changes meanwhile."""
    skipped: list[str] = field(default_factory=list)
    """Aborted scans."""
    unreadable: list[str] = field(default_factory=list)
    """Queued although their manifest could not be read (their job will fail with the reason)."""


def check_root(root) -> Path:
    """`root` as a Path when it can be a captures root: a folder that is not itself a capture (a worker pointed at
    one capture would find no scans in it and leave its queue inside the capture)."""
    root = Path(root)
    if not root.exists():  # (a link to nothing too)
        raise ConfigError(f"{root}: captures root does not exist")
    if not root.is_dir():
        raise ConfigError(f"{root}: captures root is not a folder")
    if (root / MANIFEST).is_file():
        parent = root.parent if root.name else root.resolve().parent
        raise ConfigError(f"{root} holds {MANIFEST}: it is a capture, not a captures root (use --root {parent})")
    return root


def scan_folders(root: Path) -> list[Path]:
    """Children of the root that hold a scan manifest, sorted by name; hidden folders (the queue) are left out."""
    root = Path(root)
    if not root.is_dir():
        raise CaptureError(f"{root}: captures root is not a folder")
    out = []
    for p in sorted(root.iterdir()):
        if p.name.startswith(".") or p.name == QUEUE_DIRNAME or not p.is_dir():
            continue
        if (p / MANIFEST).is_file():
            out.append(p)
    return out


SETTLE_S = 60.0
"""A scan folder whose manifest cannot be read, or that says complete and lacks measurements, is taken for a copy
still under way (cp, scp, a file manager) while anything in it changed within this many seconds: it is looked at
again on the next passes rather than queued, so that its job neither fails on a half-written manifest nor
reconstructs the chunks copied so far."""


def scan_state(folder: Path) -> str:
    """The scan's state from its manifest; raises CaptureError when the manifest is malformed."""
    from spadscan.protocol.capture_reader import CaptureReader

    return CaptureReader(folder).state


def holds_every_measurement(folder: Path) -> bool:
    """Whether a complete capture's chunks hold every measurement its manifest plans (planned poses x frames per
    pose, by the chunks' meta.json) and every chunk's arrays whole (a copy may have brought a chunk's meta.json and
    not yet all of its hists.npy); True when the manifest plans no count. False when a chunk cannot be read."""
    from spadscan.protocol.capture_reader import CaptureReader

    try:
        reader = CaptureReader(folder)
        planned, frames = reader.manifest.get("planned_poses"), reader.manifest.get("frames_per_pose", 1)
        if not (_is_int(planned) and _is_int(frames)):
            return True
        held = 0
        for name in reader.chunk_names():
            chunk = Path(folder) / name
            arrays = {chunk / "hists.npy", chunk / "poses.npy", *chunk.glob("*.npy")}
            if not all(npy_is_whole(path) for path in arrays):
                return False
            records = read_json(chunk / "meta.json").get("measurements")
            held += len(records) if isinstance(records, list) else 0
    except (OSError, ValueError, AttributeError, SpadscanError):
        return False
    return held >= planned * frames


def last_change(folder: Path) -> float:
    """The newest modification time (Unix seconds) of the folder, its entries and its chunks' files."""
    newest = 0.0
    try:
        entries = [Path(folder), *Path(folder).iterdir()]
    except OSError:
        return newest
    for entry in entries:
        try:
            newest = max(newest, entry.lstat().st_mtime)
            if entry != Path(folder) and entry.is_dir():
                newest = max([newest, *(f.lstat().st_mtime for f in entry.iterdir())])
        except OSError:
            continue
    return newest


def has_chunk(folder: Path) -> bool:
    """Whether a capture folder holds a published chunk."""
    try:
        return any(chunk_index(p.name) is not None and p.is_dir() for p in Path(folder).iterdir())
    except OSError:
        return False


def id_to_queue(queue: Queue, scan_name: str, preset: str) -> str | None:
    """The id to queue scan `scan_name`'s job under, or None when the queue holds its job already.

    That id is `job_id_for`'s, save in a queue written before ids were made one scan's each (`old_job_id_for`): there
    the scan's job may be registered under its old id (found, so it is not run again), and its own id may be held by
    another scan's job (`x+y`'s, queued as `x_y-fast`, for the scan `x_y`): it then gets its hashed id, as every
    watcher does, so that it is reconstructed too, once."""
    job_id = job_id_for(scan_name, preset)
    owner = queue.registered_scan(job_id)
    if owner is None:
        old = old_job_id_for(scan_name, preset)
        return None if old != job_id and queue.registered_scan(old) == scan_name else job_id
    if owner in (scan_name, ""):  # "": a damaged registry file, taken to be the scan's (it was before)
        return None
    hashed = job_id_for(scan_name, preset, hashed=True)
    return None if queue.known(hashed) else hashed


def scan_once(root: Path, queue: Queue, options: JobOptions, now: float | None = None) -> ScanReport:
    """One pass over the captures root: queue every complete scan that has no job yet (with `options.live`, every
    running scan with a published chunk too, as a live job). A folder that looks like a copy still under way waits
    (`SETTLE_S`); `now`: the Unix time to judge that by (default: the clock)."""
    now = time.time() if now is None else now
    report = ScanReport()
    for folder in scan_folders(root):
        job_id = id_to_queue(queue, folder.name, options.preset)
        if job_id is None:
            continue
        job = replace(options.job_for(folder.name), id=job_id)
        try:
            state = scan_state(folder)
        except CaptureError:
            state = None
        if state == "running":
            if options.live and has_chunk(folder) and queue.enqueue(replace(job, live=True)):
                report.live.append(folder.name)
            else:
                report.pending.append(folder.name)
            continue
        if state == "aborted":
            report.skipped.append(folder.name)
            continue
        unfinished = state is None or not holds_every_measurement(folder)
        quiet = now - last_change(folder)
        if unfinished and quiet < SETTLE_S:
            report.pending.append(folder.name)
            report.settling[folder.name] = SETTLE_S - quiet
            continue
        if queue.enqueue(job):
            (report.queued if state == "complete" else report.unreadable).append(folder.name)
    return report


async def watch(root: Path, queue: Queue, options: JobOptions, stop: asyncio.Event, *, poll_s: float = 2.0,
                on_report: Callable[[ScanReport], None] | None = None,
                on_error: Callable[[Exception], None] | None = None) -> None:
    """Poll the root every `poll_s` seconds until `stop` is set. The filesystem work runs in a thread.

    A pass that fails on the filesystem (a full disk while queuing, the root unmounted) goes to `on_error` and the
    next pass tries again: one bad moment must not stop scans being queued for the rest of the worker's life."""
    while not stop.is_set():
        try:
            report = await asyncio.to_thread(scan_once, root, queue, options)
        except (OSError, SpadscanError) as exc:
            if on_error is None:
                raise
            on_error(exc)
            report = None
        if on_report is not None and report is not None:
            on_report(report)
        try:
            await asyncio.wait_for(stop.wait(), poll_s)
        except asyncio.TimeoutError:
            pass
