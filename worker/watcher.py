"""Watching a captures root: every complete scan is queued once (asyncio polling, no extra dependency).

A scan folder is a child of the root that holds `scan.json`. Scans still `running` are looked at again on the next
poll; `aborted` scans are skipped; a `complete` scan is queued as the job `<scan>-<preset>`. A scan whose manifest
cannot be read is queued too, so that its job fails with the reason and `spadscan worker --status` shows it, instead
of the scan being ignored in silence. Job ids are deterministic, so polling again (or another worker polling the same
root) never queues a scan twice.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from spadscan.protocol.capture_format import MANIFEST
from spadscan.protocol.errors import CaptureError

from .jobs import Job, job_id_for
from .queue import QUEUE_DIRNAME, Queue


@dataclass(frozen=True)
class JobOptions:
    """How every scan found by the watcher is reconstructed."""

    preset: str = "fast"
    budget_s: float | None = None
    steps: int | None = None
    device: str = "auto"
    seed: int = 0

    def job_for(self, scan_name: str) -> Job:
        return Job(id=job_id_for(scan_name, self.preset), scan=scan_name, preset=self.preset,
                   budget_s=self.budget_s, steps=self.steps, device=self.device, seed=self.seed)


@dataclass
class ScanReport:
    """What one pass over the root found. Lists hold scan folder names."""

    queued: list[str] = field(default_factory=list)
    pending: list[str] = field(default_factory=list)
    """Scans still being recorded."""
    skipped: list[str] = field(default_factory=list)
    """Aborted scans."""
    unreadable: list[str] = field(default_factory=list)
    """Queued although their manifest could not be read (their job will fail with the reason)."""


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


def scan_state(folder: Path) -> str:
    """The scan's state from its manifest; raises CaptureError when the manifest is malformed."""
    from spadscan.protocol.capture_reader import CaptureReader

    return CaptureReader(folder).state


def scan_once(root: Path, queue: Queue, options: JobOptions) -> ScanReport:
    """One pass over the captures root: queue every complete scan that has no job yet."""
    report = ScanReport()
    for folder in scan_folders(root):
        job = options.job_for(folder.name)
        if queue.known(job.id):
            continue
        try:
            state = scan_state(folder)
        except CaptureError:
            state = None
        if state == "running":
            report.pending.append(folder.name)
            continue
        if state == "aborted":
            report.skipped.append(folder.name)
            continue
        if queue.enqueue(job):
            (report.queued if state == "complete" else report.unreadable).append(folder.name)
    return report


async def watch(root: Path, queue: Queue, options: JobOptions, stop: asyncio.Event, *, poll_s: float = 2.0,
                on_report: Callable[[ScanReport], None] | None = None) -> None:
    """Poll the root every `poll_s` seconds until `stop` is set. The filesystem work runs in a thread."""
    while not stop.is_set():
        report = await asyncio.to_thread(scan_once, root, queue, options)
        if on_report is not None:
            on_report(report)
        try:
            await asyncio.wait_for(stop.wait(), poll_s)
        except asyncio.TimeoutError:
            pass
