"""How far a reconstruction job has got, read from the progress bar it writes to its log (for `spadscan worker
--status`, the dashboard and the demo).

A job's process prints a tqdm bar to its log (the worker's `<queue>/logs/<job>~<claim>.log`, copied to the results'
job.log at the end), redrawn in place with carriage returns:
`reconstruct (fast):  58%|#####     | 70/120 s [01:10<00:50, loss=2.25, chamfer=1.86mm]`. The last complete bar in
the log's tail is the job's progress; its `key=value` fields (loss, chamfer, and any other the bar carries) are kept.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

TAIL_BYTES = 16 * 1024
BAR_RE = re.compile(r"(?P<desc>[^\r\n|:]+?):\s*(?P<percent>\d+)%\|[^|\r\n]*\|\s*(?P<done>[\d.]+)/(?P<total>[\d.]+)"
                    r"\s*(?P<unit>[a-z]*)\s*\[(?P<elapsed>[^<\]\r\n]*)<(?P<remaining>[^,\]\r\n]*)"
                    r"(?:,\s*(?P<fields>[^\]\r\n]*))?\]")
CHAMFER_RE = re.compile(r"^(?P<mm>[\d.]+)\s*mm$")


@dataclass(frozen=True)
class JobProgress:
    """One reading of a job's bar: `done` of `total` `unit` (seconds of a time budget, or steps), and its fields."""

    desc: str
    done: float
    total: float
    unit: str
    elapsed: str
    remaining: str
    fields: dict = field(default_factory=dict)

    @property
    def fraction(self) -> float:
        return min(1.0, self.done / self.total) if self.total > 0 else 0.0

    @property
    def chamfer_mm(self) -> float | None:
        m = CHAMFER_RE.match(self.fields.get("chamfer", ""))
        return float(m["mm"]) if m else None

    def line(self) -> str:
        """One line for a terminal or a table: what, how far, and the fields the bar shows."""
        parts = [f"{self.desc}: {self.done:.0f}/{self.total:.0f} {self.unit}".rstrip()]
        if "step" in self.fields:
            parts.append(f"step {self.fields['step']}")
        if "loss" in self.fields:
            parts.append(f"loss {self.fields['loss']}")
        if self.chamfer_mm is not None:
            parts.append(f"Chamfer {self.chamfer_mm:.2f} mm")
        parts += [f"{k} {v}" for k, v in self.fields.items() if k not in ("step", "loss", "chamfer")]
        return ", ".join(parts) + f" [{self.elapsed} elapsed, {self.remaining} left]"

    def to_dict(self) -> dict:
        return {"line": self.line(), "fraction": self.fraction, "done": self.done, "total": self.total,
                "unit": self.unit, "fields": dict(self.fields), "chamfer_mm": self.chamfer_mm}


def parse_progress(text: str) -> JobProgress | None:
    """The last complete progress bar in `text`, or None."""
    found = None
    for found in BAR_RE.finditer(text):
        pass
    if found is None:
        return None
    fields = {}
    for item in (found["fields"] or "").split(","):
        key, sep, value = item.strip().partition("=")
        if sep and key:
            fields[key] = value.strip()
    return JobProgress(found["desc"].strip(), float(found["done"]), float(found["total"]), found["unit"],
                       found["elapsed"].strip(), found["remaining"].strip(), fields)


def claim_log(queue_dir: Path, running_file: Path) -> Path:
    """The log of a running job: the worker logs a job's process to `<queue>/logs/<job>~<claim>.log`, the name of
    its `running/` file."""
    return Path(queue_dir) / "logs" / f"{Path(running_file).stem}.log"


def read_progress(log: Path, tail_bytes: int = TAIL_BYTES) -> JobProgress | None:
    """The job's progress from the tail of its log file; None when the log is missing or shows no bar yet."""
    try:
        with open(log, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - tail_bytes))
            return parse_progress(f.read().decode("utf-8", "replace"))
    except OSError:
        return None


def running_progress(queue) -> dict[str, JobProgress | None]:
    """Each running job of a queue (worker.queue.Queue) by id: its progress, or None where its log shows no bar
    yet."""
    return {job_id: read_progress(claim_log(queue.path, path))
            for job_id, (state, path) in queue.job_paths().items() if state == "running"}


def progress_field(state: str, job_id: str, running: dict) -> dict:
    """What a job's entry in a JSON listing of the queue adds (`spadscan worker --status --json`, the dashboard):
    {"progress": its bar as a dict, or None before the bar's first line} for a running job (`running`:
    running_progress), {} for the others."""
    if state != "running" or job_id not in running:
        return {}
    progress = running[job_id]
    return {"progress": progress.to_dict() if progress else None}
