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

from .errors import ReconstructionError
from .model_api import ReconModel, RunPlan


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


def train(model: ReconModel, plan: RunPlan, *, checkpoints: int = 12, every_s: float | None = None,
          evaluate: Callable[[], dict] | None = None, scoring_in_budget: bool = True,
          on_checkpoint: Callable[[list[dict]], None] | None = None, progress: bool = True,
          desc: str = "reconstruct", score_note: str = "", early_stop: bool = False) -> TrainResult:
    """Run model.step() until plan.steps steps or plan.budget_s seconds, whichever comes first; with `early_stop`,
    also as soon as a step reports `converged: True` (stopped_by 'converged'). The budget counts training and
    checkpoint evaluation together, or training alone when `scoring_in_budget` is False (then no evaluation is
    skipped).

    Checkpoints: at the start, every `every_s` seconds of training (default: every 1/checkpoints of the budget when
    there is one, else of the steps; 0: after every step) and at the end; each records the step, training seconds,
    the mean loss since the previous checkpoint and whatever `evaluate()` returns. `on_checkpoint(trace)` sees the
    trace after each one (a benchmark keeps it on disk as it goes). A tqdm bar on stderr shows progress unless
    `progress` is False: `loss=`, and with an evaluation `chamfer=` (the last checkpoint's) and `scored=` with
    `score_note`, how checkpoints are scored (coarser than the final mesh). The lab dashboard reads these fields
    from a job's log: keep them `key=value` without commas."""
    if not plan.steps and not plan.budget_s:
        raise ReconstructionError("a run needs a step count or a time budget (give --steps or --budget-s)")
    if every_s is not None and not (math.isfinite(every_s) and every_s >= 0):
        raise ReconstructionError(f"checkpoint interval {every_s} s must be finite and >= 0")
    by_time = bool(plan.budget_s)
    marks_by_time = by_time or every_s is not None
    if every_s is not None:
        every = every_s
    else:
        every = plan.budget_s / checkpoints if by_time else max(1, math.ceil(plan.steps / checkpoints))
    result = TrainResult(steps=0, seconds=0.0, stopped_by="", last={})
    window: list[float] = []

    eval_cost = [0.0]  # the last evaluation's seconds: what the next one is expected to take

    def spent() -> float:
        return result.seconds + (result.eval_seconds if scoring_in_budget else 0.0)

    def checkpoint(final: bool = False):
        t0 = time.perf_counter()
        entry = {"step": result.steps, "seconds": round(result.seconds, 4),
                 "loss": (sum(window) / len(window)) if window else None}
        if evaluate is not None:
            if final or not (by_time and scoring_in_budget) or spent() + eval_cost[0] <= plan.budget_s:
                entry.update(evaluate())
                eval_cost[0] = time.perf_counter() - t0
            else:
                entry["note"] = "evaluation skipped: it would not fit in the time budget"
        result.trace.append(entry)
        window.clear()
        result.eval_seconds += time.perf_counter() - t0
        if on_checkpoint is not None:
            on_checkpoint(result.trace)
        return entry

    total = plan.budget_s if by_time else plan.steps
    unit = "s" if by_time else "step"
    with tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, disable=not progress, leave=False,
              bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} " + unit + " [{elapsed}<{remaining}{postfix}]") as bar:
        checkpoint()
        next_mark = every
        while True:
            if plan.steps and result.steps >= plan.steps:
                result.stopped_by = "steps"
                break
            if by_time and spent() >= plan.budget_s:
                result.stopped_by = "budget"
                break
            t0 = time.perf_counter()
            last = model.step()
            dt = time.perf_counter() - t0
            result.steps += 1
            result.seconds += dt
            result.last = last
            result.losses.append(float(last["loss"]))
            if early_stop and last.get("converged"):
                result.stopped_by = "converged"
            window.append(float(last["loss"]))
            bar.update(min(spent() - bar.n, max(0.0, plan.budget_s - bar.n)) if by_time else 1)
            done = result.seconds if marks_by_time else result.steps
            if done >= next_mark:
                entry = checkpoint()
                next_mark += every
                post = {"loss": f"{entry['loss']:.3g}"}
                if entry.get("chamfer_mm") is not None:
                    post["chamfer"] = f"{entry['chamfer_mm']:.2f}mm"
                    if score_note:
                        post["scored"] = score_note
                bar.set_postfix(post)
            if result.stopped_by:
                break
        if window or not result.trace or result.trace[-1]["step"] != result.steps:
            checkpoint(final=True)
        elif evaluate is not None and "note" in result.trace[-1]:
            # The run ended on a checkpoint whose evaluation was skipped: the end of a run is always evaluated.
            t0 = time.perf_counter()
            last = result.trace[-1]
            del last["note"]
            last.update(evaluate())
            result.eval_seconds += time.perf_counter() - t0
            if on_checkpoint is not None:
                on_checkpoint(result.trace)
    return result
