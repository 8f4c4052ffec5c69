"""How far a reconstruction job has got, read from the progress bar it writes to its log (for `spadscan worker
--status`, the dashboard and the demo).

A job's process prints a tqdm bar to its log (the worker's `<queue>/logs/<job>~<claim>.log`, copied to the results'
job.log at the end), redrawn in place with carriage returns:
`reconstruct (fast):  58%|#####     | 70/120 s [01:10<00:50, loss=2.25, chamfer=1.86mm]`. The last complete bar in
the log's tail is the job's progress; its `key=value` fields (loss, chamfer, and any other the bar carries) are kept.

That bar counts the training only: what a job's `budget_s` leaves it once set up, less what its mesh, metrics and
pictures will take. A running job with a budget is therefore shown against that budget (`JobProgress.budget_s`,
`spent_s`: from its claim, or for a live job from its scan's end, when its final run starts), so that the bar is not
full, "00:00 left", while a third of the job is still to run; once training is over the line says what the job does
then. A job without a budget shows its training bar as it is.
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.live_status import LiveStatus

from .jobs import Job
from .queue import QUEUE_DIRNAME, SEP, Claim
from .recon.trainer import ENDED_FIELD
from .status_detail import ENDED, own_live_status

TAIL_BYTES = 16 * 1024
BAR_RE = re.compile(r"(?P<desc>[^\r\n|:]+?):\s*(?P<percent>\d+)%\|[^|\r\n]*\|\s*(?P<done>[\d.]+)/(?P<total>[\d.]+)"
                    r"\s*(?P<unit>[a-z]*)\s*\[(?P<elapsed>[^<\]\r\n]*)<(?P<remaining>[^,\]\r\n]*)"
                    r"(?:,\s*(?P<fields>[^\]\r\n]*))?\]")
CHAMFER_RE = re.compile(r"^(?P<mm>[\d.]+)\s*mm$")
SCORED_RE = re.compile(r"^at step (?P<step>\d+)")
"""The bar's `scored=` field: the step its `chamfer=` was scored at (then how checkpoints are scored)."""
AFTER_TRAINING = "training done: mesh, metrics, pictures"
"""What a job does once its training is over (`JobProgress.training_done`; its result is not there yet)."""
PROGRESS_S = 30.0
"""How often `spadscan worker` says each running job's progress in its own terminal (`ProgressNotes`)."""
SETTING_UP = "setting up"
"""A job's stage before its log shows a bar (or, for a live job, before its live status is written)."""


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
    budget_s: float | None = None
    """The job's own budget (set-up, training, mesh, metrics, pictures), when it has one and its start is known."""
    spent_s: float | None = None
    """Seconds of that budget gone when the bar was read."""

    @property
    def training_done(self) -> bool:
        """The count at its total, or the bar's field that the training ended (a run that converged early, a
        budget's last step short of it: the job makes its mesh, metrics and pictures all the same)."""
        return (self.total > 0 and self.done >= self.total) or ENDED_FIELD in self.fields

    @property
    def fraction(self) -> float:
        """How far the job has got, 0 to 1: of its budget where known (the training bar ends before the job
        does), else of its training bar."""
        if self.budget_s is not None and self.spent_s is not None:
            return min(1.0, max(0.0, self.spent_s / self.budget_s))
        return min(1.0, self.done / self.total) if self.total > 0 else 0.0

    @property
    def chamfer_mm(self) -> float | None:
        m = CHAMFER_RE.match(self.fields.get("chamfer", ""))
        return float(m["mm"]) if m else None

    @property
    def chamfer_step(self) -> int | None:
        """The step the bar's Chamfer was scored at (a bar of an earlier version does not say)."""
        m = SCORED_RE.match(self.fields.get("scored", ""))
        return int(m["step"]) if m else None

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
        return ", ".join(parts) + f" [{self.when()}]"

    def when(self) -> str:
        """How far in time: of the job's budget where known, else the training bar's elapsed and left."""
        stage = [AFTER_TRAINING] if self.training_done else []
        if self.budget_s is not None and self.spent_s is not None:
            return "; ".join(stage + [of_budget(self.spent_s, self.budget_s)])
        if stage:  # its own "00:00 left" would say the job is over: it is not, until its result is published
            return f"{AFTER_TRAINING} (training took {self.elapsed})"
        return f"{self.elapsed} elapsed, {self.remaining} left"

    def to_dict(self) -> dict:
        return {"line": self.line(), "fraction": self.fraction, "done": self.done, "total": self.total,
                "unit": self.unit, "fields": dict(self.fields), "chamfer_mm": self.chamfer_mm,
                "chamfer_step": self.chamfer_step,
                "training_done": self.training_done, "budget_s": self.budget_s, "spent_s": self.spent_s}


def of_budget(spent_s: float, budget_s: float) -> str:
    """'01:10 of the job's 02:00 budget, 00:50 left' (or '00:03 over')."""
    left = budget_s - spent_s
    tail = f"{clock(left)} left" if left >= 0 else f"{clock(-left)} over"
    return f"{clock(spent_s)} of the job's {clock(budget_s)} budget, {tail}"


def clock(seconds: float) -> str:
    """Seconds as a bar shows them: mm:ss, or h:mm:ss from an hour on."""
    whole = max(0, round(seconds))
    hours, rest = divmod(whole, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60:02d}:{rest % 60:02d}"


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


class LogTails:
    """`read_progress` for a worker that looks at its running jobs' logs at every turn of its loop (every poll, and
    whenever a job ends): a log is read again only when it has changed (its file, size or modification time), else
    its last reading stands. A job's bar is redrawn by appending, so its log grows with every new reading."""

    def __init__(self):
        self._seen: dict[Path, tuple[tuple[int, int, int], JobProgress | None]] = {}
        """Log -> (its file, size and mtime when read, what it showed)."""

    def read(self, log: Path) -> JobProgress | None:
        """What `read_progress(log)` would say now."""
        try:
            st = os.stat(log)
        except OSError:
            self._seen.pop(log, None)
            return None
        key = (st.st_ino, st.st_size, st.st_mtime_ns)
        seen = self._seen.get(log)
        if seen is not None and seen[0] == key:
            return seen[1]
        progress = read_progress(log)
        self._seen[log] = (key, progress)
        return progress

    def keep_only(self, logs) -> None:
        """Forget the logs of jobs no longer running."""
        for log in set(self._seen) - set(logs):
            del self._seen[log]


def running_progress(queue, root=None, now: float | None = None) -> dict[str, JobProgress | None]:
    """Each running job of a queue (worker.queue.Queue) by id: its progress, or None where its log shows no bar
    yet; a job with a budget is measured against it (`job_budget`). `root`: the captures root (default: the folder
    of a queue named .queue), where a live job's status says when its final run started; `now`: time.time()."""
    if root is None and queue.path.name == QUEUE_DIRNAME:
        root = queue.path.parent
    now = time.time() if now is None else now
    found = {}
    for job_id, (state, path) in queue.job_paths().items():
        if state != "running":
            continue
        progress = read_progress(claim_log(queue.path, path))
        found[job_id] = measured(progress, job_budget(queue, job_id, path, root) if progress else None, now)
    return found


def measured(progress: JobProgress | None, budget: tuple[float, float] | None, now: float) -> JobProgress | None:
    """`progress` measured against `budget` ((budget_s, when it started counting, unix seconds), or None: as it is)
    at `now` (unix seconds)."""
    if progress is None or budget is None:
        return progress
    budget_s, start = budget
    return replace(progress, budget_s=budget_s, spent_s=max(0.0, now - start))


def job_budget(queue, job_id: str, running_file: Path, root) -> tuple[float, float] | None:
    """(budget_s, when it started counting, unix seconds) of a running job, or None when it has no budget or that
    start is not known (`claim_budget`); an ordinary job's process started when its claim's record was written."""
    try:
        job = Job.from_dict(json.loads(Path(running_file).read_text()), str(running_file))
    except (OSError, ValueError, SpadscanError):
        return None
    started = None
    if not job.live:
        token = Path(running_file).stem.rpartition(SEP)[2]
        record = next((r for r in queue.read_records(job_id)[0] if r.get("token") == token), {})
        started = record.get("started_unix")
    return claim_budget(job, started, root)


def claim_budget(job: Job, started: float | None, root) -> tuple[float, float] | None:
    """(budget_s, when it started counting, unix seconds) of a running job, or None when it has no budget or that
    start is not known. An ordinary job's budget counts from its process's start (`started`, unix seconds); a live
    job's bounds its final run, from the scan's end: when its live status turned 'final' (`root`: the captures
    root)."""
    if not _positive(job.budget_s):
        return None
    start = final_run_start(root, job) if job.live else started
    return (float(job.budget_s), float(start)) if _finite(start) else None


def final_run_start(root, job: Job) -> float | None:
    """When a live job's final run started (unix seconds): its live status is written 'final' just before; None
    while it follows its scan, or when that status is not its own or cannot be read."""
    status = own_live_status(root, job, ("final",))
    return None if status is None else written_unix(status)


def ended_live_status(root, job: Job, since: float) -> LiveStatus | None:
    """The live status of running live job `job` when it says how the job ended (ENDED: its scan was aborted, it
    stopped), written since its claim began (`since`, unix seconds): an earlier attempt's last word is none of this
    one's. The job's process ends right after writing it; until the worker has reaped it, that is what the job is
    doing (not setting up). None otherwise; `root`: the captures root."""
    status = own_live_status(root, job, ENDED)
    if status is None:
        return None
    written = written_unix(status)
    return status if written is not None and written >= since else None


def written_unix(status: LiveStatus) -> float | None:
    """When `status` was written (unix seconds, from its `updated_utc`); None when that cannot be read."""
    then = status.updated()
    return None if then is None else then.timestamp()


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _positive(value) -> bool:
    return _finite(value) and value > 0


def progress_field(state: str, job_id: str, running: dict) -> dict:
    """What a job's entry in a JSON listing of the queue adds (`spadscan worker --status --json`, the dashboard):
    {"progress": its bar as a dict, or None before the bar's first line} for a running job (`running`:
    running_progress), {} for the others."""
    if state != "running" or job_id not in running:
        return {}
    progress = running[job_id]
    return {"progress": progress.to_dict() if progress else None}


@dataclass(frozen=True)
class ProgressNote:
    """What a running job is doing, for the worker's own terminal: `stage` (set-up, training, what follows it, a live
    job's state) and `text`, one line."""

    stage: str
    text: str


def progress_note(claim: Claim, log: Path, root, now: float | None = None,
                  tails: LogTails | None = None) -> ProgressNote:
    """The progress line of the job `claim` holds, from its `log` (its bar, measured against its budget as --status
    measures it), else, for a live job following its scan or ending (its scan aborted: `ended_live_status`), its live
    status; else that it is setting up. `root`: the captures root; `now`: time.time(); `tails`: where the log's last
    reading is kept (None: the log is read)."""
    job = claim.job
    now = time.time() if now is None else now
    budget = claim_budget(job, claim.started, root)
    progress = measured(tails.read(log) if tails is not None else read_progress(log), budget, now)
    if progress is not None:
        stage = f"{progress.desc}: {AFTER_TRAINING if progress.training_done else 'training'}"
        return ProgressNote(stage, f"{job.id} at {100 * progress.fraction:.0f} %: {progress.line()}")
    live = None
    if job.live:
        live = own_live_status(root, job) or ended_live_status(root, job, claim.started)
    if live is not None:
        return ProgressNote(f"live: {live.state}", f"{job.id}: {live.summary()}")
    when = of_budget(now - budget[1], budget[0]) if budget else f"{clock(now - claim.started)} since it started"
    return ProgressNote(SETTING_UP, f"{job.id}: setting up, no progress bar in its log yet [{when}]")


class ProgressNotes:
    """Which progress lines the worker says in its own terminal: each running job's line every `interval_s`
    seconds, and at once when its stage changes (its training starts or ends, a live job's state changes), never
    more than one line per job at a look. A job's set-up goes unsaid until the interval has passed: its 'started'
    line has just said it."""

    def __init__(self, interval_s: float = PROGRESS_S):
        self.interval_s = interval_s
        self.said: dict[str, tuple[float, str]] = {}
        """Claim token -> (time.monotonic() of its job's last line, or of its first look; the stage it said)."""

    def due(self, token: str, note: ProgressNote, now: float | None = None) -> bool:
        """Whether `note` (of the job claim `token` holds) is to be said now (`now`: time.monotonic())."""
        now = time.monotonic() if now is None else now
        last = self.said.get(token)
        if last is None and note.stage == SETTING_UP:
            self.said[token] = (now, note.stage)
            return False
        if last is not None and note.stage == last[1] and now - last[0] < self.interval_s:
            return False
        self.said[token] = (now, note.stage)
        return True

    def keep_only(self, tokens) -> None:
        """Forget the claims that are no longer running."""
        for token in set(self.said) - set(tokens):
            del self.said[token]
