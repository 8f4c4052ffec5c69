"""The one training loop of every preset, for `spadscan reconstruct`, the worker and the benchmarks: steps until the
step count or the time budget runs out (or, with `early_stop`, until the model reports `converged`), with checkpoints
at regular intervals that record the loss and (through a callback) the error.

The training clock counts only `model.step()`; checkpoint evaluation (mesh extraction, Chamfer) is timed apart and
never charged to the trace, so that error-versus-time curves compare methods fairly. By default the time budget
bounds the wall time of the whole loop, evaluation included: a run with ground truth ends when its budget is spent,
and a checkpoint whose evaluation would not fit in what is left records its loss only. A benchmark that compares
methods at equal training time leaves the scoring out of the budget (`scoring_in_budget=False`).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from typing import Callable

from tqdm import tqdm

from ..cpu_wait import ThreadWaits
from .errors import ReconstructionError
from .model_api import ReconModel, RunPlan


PROGRESS_LINES = "lines"
"""`train(progress=PROGRESS_LINES)`: the bar's readings as plain lines (`ProgressLines`), not a bar."""
ENDED_FIELD = "ended"
"""The bar's field, drawn once its training has ended, that says why: converged, budget, steps or interrupted."""
LINE_SHARE = 0.1
"""A progress line each time training passes another tenth of its bar: a run's log shows its course in ten lines
whatever its length."""
LINE_EVERY_S = 30.0
"""And at least this often (wall seconds), as `spadscan worker` says its jobs' progress: a run of hours still shows
in its log that it is alive without filling it (120 lines an hour)."""


@dataclass
class TrainResult:
    """What a run did. trace: one dict per checkpoint {step, seconds, loss, ...evaluation}."""

    steps: int
    seconds: float
    stopped_by: str
    last: dict
    trace: list[dict] = field(default_factory=list)
    eval_seconds: float = 0.0
    losses: list[float] = field(default_factory=list)
    data_terms: list[float] = field(default_factory=list)
    """Each step's data term (its 'data', or its loss where the model reports no data term)."""
    cpu_seconds: float = 0.0
    """Process CPU seconds (all threads) spent in the steps, against `seconds` of wall time: under 1 CPU second a
    second, the process did not get a whole core."""


def train(model: ReconModel, plan: RunPlan, *, checkpoints: int = 12, every_s: float | None = None,
          evaluate: Callable[[], dict] | None = None, scoring_in_budget: bool = True,
          on_checkpoint: Callable[[list[dict]], None] | None = None, progress: bool | str = True,
          desc: str = "reconstruct", score_note: str = "", early_stop: bool = False,
          on_step: Callable[[float], None] | None = None, clock: Callable[[], float] = time.perf_counter,
          cpu_clock: Callable[[], float] = time.process_time, max_eval_share: float = 0.25,
          eval_estimate_s: float = 0.0, end_evaluation: Callable[[float], bool] | None = None,
          stop: Callable[[], bool] | None = None, waits: ThreadWaits | None = None) -> TrainResult:
    """Run model.step() until plan.steps steps or plan.budget_s seconds, whichever comes first; with `early_stop`,
    also as soon as a step reports `converged: True` (stopped_by 'converged'). The budget counts training and
    checkpoint evaluation together, or training alone when `scoring_in_budget` is False (then no evaluation is
    skipped). Counted in the budget, evaluations take at most `max_eval_share` of it: one that would take more, or
    not fit in what is left, is skipped (its checkpoint records the loss only); `eval_estimate_s` is what the first
    one is expected to take (later ones: what the last one took). The end of a run is evaluated unless
    `end_evaluation(expected seconds)` says there is no time for it (a whole-run budget nearly spent).

    Checkpoints: at the start, every `every_s` seconds of training (default: every 1/checkpoints of the budget when
    there is one, else of the steps; 0: after every step) and at the end; each records the step, training seconds,
    the mean loss since the previous checkpoint and whatever `evaluate()` returns. `on_checkpoint(trace)` sees the
    trace after each one (a benchmark keeps it on disk as it goes). A tqdm bar on stderr shows progress when
    `progress` is True, wherever stderr goes (a worker's job writes it into its log, which job_progress.py reads);
    PROGRESS_LINES: plain lines instead (`ProgressLines`, for a log a person reads); False: nothing. The bar counts
    seconds of `plan.budget_s` (with a budget) or steps, and shows `step=` and `loss=`, and with an evaluation
    `chamfer=` (the last scored checkpoint's) and `scored=`, the step it was scored at and `score_note`, how
    checkpoints are scored (coarser than the final mesh): under a short budget the scoring's share can be spent
    early, and a Chamfer many steps old must say so. The lab dashboard and the demo read these fields from a job's
    log: keep them `key=value` without commas.

    `on_step(seconds)` sees each step's wall time (the thread governor). `stop()`, asked before each step, true: the
    user asked training to end now (a first Ctrl-C of `spadscan reconstruct`); the run ends as a budget ends it, its
    mesh and report made (stopped_by 'interrupted'). `clock` (wall seconds) and `cpu_clock` (this process's CPU
    seconds) time the steps; tests inject their own."""
    if not plan.steps and not plan.budget_s:
        raise ReconstructionError("a run needs a step count or a time budget (give --steps or --budget-s)")
    if every_s is not None and not (math.isfinite(every_s) and every_s >= 0):
        raise ReconstructionError(f"checkpoint interval {every_s} s must be finite and >= 0")
    if progress not in (True, False, PROGRESS_LINES):
        raise ReconstructionError(f"progress {progress!r} must be True (a bar), False or {PROGRESS_LINES!r}")
    by_time = bool(plan.budget_s)
    marks_by_time = by_time or every_s is not None
    if every_s is not None:
        every = every_s
    else:
        every = plan.budget_s / checkpoints if by_time else max(1, math.ceil(plan.steps / checkpoints))
    result = TrainResult(steps=0, seconds=0.0, stopped_by="", last={})
    window: list[float] = []

    eval_cost = [float(eval_estimate_s)]  # the last evaluation's seconds: what the next one is expected to take

    def spent() -> float:
        return result.seconds + (result.eval_seconds if scoring_in_budget else 0.0)

    def checkpoint(final: bool = False):
        t0 = clock()
        entry = {"step": result.steps, "seconds": round(result.seconds, 4),
                 "loss": (sum(window) / len(window)) if window else None}
        if evaluate is not None:
            if final:
                due = end_evaluation is None or end_evaluation(eval_cost[0])
            elif by_time and scoring_in_budget:
                due = (spent() + eval_cost[0] <= plan.budget_s
                       and result.eval_seconds + eval_cost[0] <= max_eval_share * plan.budget_s)
            else:
                due = True
            if due:
                entry.update(evaluate())
                eval_cost[0] = clock() - t0
            else:
                entry["note"] = "evaluation skipped: it would not fit in the time budget"
        result.trace.append(entry)
        window.clear()
        result.eval_seconds += clock() - t0
        if on_checkpoint is not None:
            on_checkpoint(result.trace)
        return entry

    # Read around the stretches of steps between checkpoints, not around each step: a reading costs a fraction of a
    # millisecond, a few per cent of a short step.
    resume, pause = (waits.resume, waits.pause) if waits is not None else (lambda: None, lambda: None)
    total = plan.budget_s if by_time else plan.steps
    unit = "s" if by_time else "step"
    # What a budget's seconds on the bar are: training's, and checkpoint scoring's where the budget counts it (the
    # report's `seconds` are the steps' alone: the lines must not call the sum "training").
    what = SCORING_COUNTED if by_time and evaluate is not None and scoring_in_budget else None
    with progress_display(progress, total, desc, unit, clock, what) as bar:
        checkpoint()
        next_mark = every
        post: dict[str, str] = {}
        resume()
        while True:
            if plan.steps and result.steps >= plan.steps:
                result.stopped_by = "steps"
                break
            if by_time and result.steps and spent() >= plan.budget_s:  # every run makes at least one step
                result.stopped_by = "budget"
                break
            if stop is not None and stop() and result.steps:
                result.stopped_by = "interrupted"
                break
            t0, c0 = clock(), cpu_clock()
            last = model.step()
            dt = clock() - t0
            result.cpu_seconds += cpu_clock() - c0
            result.steps += 1
            result.seconds += dt
            result.last = last
            result.losses.append(float(last["loss"]))
            result.data_terms.append(float(last.get("data", last["loss"])))
            if on_step is not None:
                on_step(dt)
            if early_stop and last.get("converged"):
                result.stopped_by = "converged"
            window.append(float(last["loss"]))
            post["step"] = str(result.steps)
            post["loss"] = f"{sum(window) / len(window):.3g}"  # the mean since the last checkpoint, as the trace's
            bar.set_postfix(post, refresh=False)  # drawn with the next update
            bar.update(min(spent() - bar.n, max(0.0, plan.budget_s - bar.n)) if by_time else 1)
            done = result.seconds if marks_by_time else result.steps
            if done >= next_mark:
                pause()
                entry = checkpoint()
                resume()
                next_mark += every
                if entry.get("chamfer_mm") is not None:
                    post["chamfer"] = f"{entry['chamfer_mm']:.2f}mm"
                    # the step it was scored at: a checkpoint whose scoring did not fit the budget leaves it as it was
                    post["scored"] = f"at step {entry['step']}" + (f"; {score_note}" if score_note else "")
                bar.set_postfix(post)
            if result.stopped_by:
                break
        pause()
        # The bar says its training ended, and why: its count need not be at its total (a run that converged early, a
        # budget's last step that left part of a second), and what reads it from a job's log (worker.job_progress)
        # tells the mesh, metrics and pictures that follow from training by this field.
        post[ENDED_FIELD] = result.stopped_by
        bar.set_postfix(post)  # the last step's fields are drawn, whenever the bar last was
        if window or not result.trace or result.trace[-1]["step"] != result.steps:
            checkpoint(final=True)
        elif evaluate is not None and "note" in result.trace[-1] and (end_evaluation is None
                                                                       or end_evaluation(eval_cost[0])):
            # The run ended on a checkpoint whose evaluation was skipped: the end of a run is always evaluated.
            t0 = clock()
            last = result.trace[-1]
            del last["note"]
            last.update(evaluate())
            result.eval_seconds += clock() - t0
            if on_checkpoint is not None:
                on_checkpoint(result.trace)
    return result


def progress_display(progress: bool | str, total: float, desc: str, unit: str, clock: Callable[[], float],
                     what: str | None = None):
    """What shows a run's progress on stderr: `ProgressLines` for PROGRESS_LINES (`what`: what its count is, as
    `ProgressLines` takes it), else a tqdm bar (drawn when `progress` is True). Both take `update(n)`,
    `set_postfix(fields, refresh)` and `n`, and are context managers."""
    if progress == PROGRESS_LINES:
        return ProgressLines(total, desc, unit, clock, sys.stderr, what=what)
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, disable=not progress, leave=False,
                bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} " + unit + " [{elapsed}<{remaining}{postfix}]")


SCORING_COUNTED = "s of training and checkpoint scoring"
"""What a ProgressLines count of seconds is where a time budget counts checkpoint scoring too (its `what`)."""


class ProgressLines:
    """A bar's readings as plain newline-terminated lines, for a log that a person reads (stderr a file or a pipe): a
    bar redraws itself with carriage returns, and a file keeps every frame. A line each time the count passes another
    `share` of `total`, or `every_s` wall seconds after the last line; the end (the count at its total) is said once,
    by close(), with the fields as they are then: a run that ends on a checkpoint sets its Chamfer after its last
    count. E.g. `reconstruct (fast): 4.0/10.0 s of training (40 %), step 120, loss 2.25 [00:05]` (with a time budget
    the total is training's share of it, as on the bar). `clock`: wall seconds; `file` None: nothing is said. `what`:
    what the count is, after the numbers (default: "s of training" for seconds, else the unit's plural; "s of
    training and checkpoint scoring" where the budget counts the scoring too).

    It takes what the trainer and the demo ask of a tqdm bar: update(n), set_postfix(fields, refresh),
    set_postfix_str(text), set_description_str(text), reset(), close(), n, desc and total (which the demo sets to a
    job's own), and it is a context manager."""

    def __init__(self, total: float, desc: str, unit: str, clock: Callable[[], float], file,
                 share: float = LINE_SHARE, every_s: float = LINE_EVERY_S, what: str | None = None):
        self.desc, self.unit, self.clock, self.file = desc, unit, clock, file
        self.what = what or ("s of training" if unit == "s" else f"{unit}s")
        self.share = share
        self.every_s = every_s
        self.n = 0.0
        self.postfix = ""
        """What the lines say after the count: set_postfix's `key value` pairs, or set_postfix_str's text."""
        self.start = clock()
        self.last_at = self.start
        self.total = total
        self.said: tuple | None = None
        """(count, description, postfix) of the last line said."""

    @property
    def total(self) -> float:
        return self._total

    @total.setter
    def total(self, total: float) -> None:
        # The demo learns a job's own total after its bar was made: the tenths are the new total's from here on.
        self._total = total
        self.step = self.share * total
        self.next_n = self._next_mark()

    def __enter__(self) -> ProgressLines:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:  # a run that failed or was aborted says so itself, not a reading of how far it got
            self.close()

    def set_postfix(self, fields: dict, refresh: bool = True) -> None:
        """The fields the next line shows (`refresh` is tqdm's: a line comes only with the count)."""
        self.postfix = ", ".join(f"{key} {value}" for key, value in fields.items())

    def set_postfix_str(self, text: str) -> None:
        """What the next line shows after the count, as it is."""
        self.postfix = text

    def set_description_str(self, desc: str) -> None:
        """The words the next line starts with. A new description once the count has begun (the demo's "mesh,
        metrics, pictures, report" stage, at the count where training ended) is said at once: no count may come after
        it, and the stage may take a while (said at close() only, a log would be silent through it and date its line
        after it). One at the start (a retry naming its attempt) comes with the first count."""
        changed, self.desc = desc != self.desc, desc
        if changed and self.n > 0:
            self._say(self.clock())

    def reset(self) -> None:
        """The count and its clock back to zero, the total kept (tqdm's reset: the demo's bar for a job's next
        attempt, which trains from nothing); the last reading first, where no line said it (the end of the attempt
        before, say)."""
        if self.n > 0:
            self.close()
        self.n = 0.0
        self.start = self.last_at = self.clock()
        self.next_n = self._next_mark()
        self.said = None

    def update(self, n: float) -> None:
        """Count `n` more; say a line when one is due, unless the count reached the end: close() says that."""
        self.n += n
        if self._at_end():
            return
        now = self.clock()
        if (self.step > 0 and self.n >= self.next_n) or now - self.last_at >= self.every_s:
            self._say(now)

    def close(self) -> None:
        """The last reading, unless the last line said it already."""
        if self.said != (self.n, self.desc, self.postfix):
            self._say(self.clock())

    def line(self, now: float) -> str:
        what = self.what
        # A short run's tenths are not whole seconds; a budget that set-up all but spent leaves hundredths.
        digits = (2 if self.total < 1 else 1 if self.total < 100 else 0) if self.unit == "s" else 0
        percent = f" ({100 * self.n / self.total:.0f} %)" if self.total > 0 else ""
        parts = [f"{self.desc}: {self.n:.{digits}f}/{self.total:.{digits}f} {what}{percent}"]
        parts += [self.postfix] if self.postfix else []
        return ", ".join(parts) + f" [{tqdm.format_interval(now - self.start)}]"

    def _at_end(self) -> bool:
        # Within rounding: a budget's last update adds what is left of it (budget - n) to n.
        return self.total > 0 and self.n >= self.total * (1 - 1e-9)

    def _next_mark(self) -> float:
        """The count at which the next tenth's line is due."""
        return (math.floor(self.n / self.step + 1e-9) + 1) * self.step if self.step > 0 else math.inf

    def _say(self, now: float) -> None:
        if self.file is not None:
            try:
                print(self.line(now), file=self.file, flush=True)
            except (OSError, ValueError):
                # The reader is gone (`... 2>&1 | head`, a closed log): the run goes on to its result, unsaid.
                self.file = None
        self.said = (self.n, self.desc, self.postfix)
        self.last_at = now
        self.next_n = self._next_mark()
