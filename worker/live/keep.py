"""Which field a live job's final run meshes: its own, or the live fit's it started from, whichever explains the
measurements better.

The final run is short (it polishes the live fit for a few seconds' steps, or within the job's budget), and it may
end worse than it began. So once it has trained, before its mesh, metrics and pictures, both fields are scored on
the same views of the complete capture with the same rays (the data term, deviance per bin:
`FastModel.deviance_all_views`): every view of a capture of up to 256 views, and of a larger one the 256 views spread
over it that its set-up read (`problem.setup_views`), whose per-bin mean estimates every view's. The model is left
holding the better one: the mesh, the report's pictures, its fit check and its metrics all describe what is
published. report.json says which (`published`).

Each field is scored as it was fitted: with its own albedos (and table offset), and on its own grid. A
final run from the hull that its budget ended on the coarse level fitted its albedo to the hull's bloated surface,
and a fine live field read on the coarse grid loses the parts that grid cannot hold: scored on the final run's grid
and albedo, a live fit of 1.8 mm read 86 per bin against 28 for a 40 mm final field, and the final one was
published; on its own grid and albedo it reads 21 against 28.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch

SCORE_SEED = 0
"""The rays both fields are scored on."""


@dataclass
class LiveState:
    """What the live fit hands the final run: its field (a GridField that later steps leave as it is), the level of
    refinement it reached, and its fitted numbers besides the grid (`FastModel.fitted_scalars`, copies)."""

    field: object
    level: int
    scalars: list[torch.Tensor]


def keep_the_better(model, live: LiveState, log: Callable[[str], None]) -> dict:
    """Score the final model's mesh field and the live one (projected into the final model's hull, as at the warm
    start) on the same views (the module docstring), each on its own grid with its own fitted numbers, and leave the
    better one in `model` (the field it meshes, its albedos; the grid refined to the live fit's level where that is
    finer, the final field then upsampled onto it: the same surface). Returns report.json's `published`: which
    field, and both deviances per bin."""
    use_field(model, model.mesh_field().sdf.detach().clone())
    final_dev = model.deviance_all_views(SCORE_SEED)
    final_scalars = scalars_of(model)
    while model.level < live.level and model.part("refinement") is not None:
        model.refine()  # the final surface as it is, on the live fit's finer grid
    final_values = model.field.sdf.detach().clone()
    model.warm_start(live.field, model.level, model.level_steps)
    use_scalars(model, live.scalars)
    live_dev = model.deviance_all_views(SCORE_SEED)
    # A non-finite deviance (a field that diverged) never wins, nor goes into report.json as a number.
    live_better = math.isfinite(live_dev) and (live_dev < final_dev or not math.isfinite(final_dev))
    which = "live" if live_better else "final"
    if which == "final":
        use_field(model, final_values)
        use_scalars(model, final_scalars)
    log(f"live: publishing the {which} field (deviance per bin: live {live_dev:.4f}, final {final_dev:.4f})")
    return {"published": {"mesh": which, "deviance_live": _rounded(live_dev), "deviance_final": _rounded(final_dev)}}


def _rounded(deviance: float) -> float | None:
    """A deviance as report.json keeps it: 5 decimals, None where it is not finite."""
    return round(deviance, 5) if math.isfinite(deviance) else None


def use_field(model, values) -> None:
    """Set the model's grid (and the field it meshes) to `values`, of the grid's own shape."""
    with torch.no_grad():
        model.field.sdf.copy_(values)
    model.jumped()


def scalars_of(model) -> list[torch.Tensor]:
    """Copies of the model's fitted numbers besides the grid (`FastModel.fitted_scalars`)."""
    return [t.detach().clone() for t in model.fitted_scalars()]


def use_scalars(model, values: list[torch.Tensor]) -> None:
    """Set the model's fitted numbers besides the grid to `values`, in order, where their shapes agree (a model
    of another scene may fit a table the other does not: the object's albedo, first, is always taken)."""
    with torch.no_grad():
        for own, value in zip(model.fitted_scalars(), values):
            if own.shape == value.shape:
                own.copy_(value.to(own.device, own.dtype))


__all__ = ["LiveState", "keep_the_better", "scalars_of", "use_field", "use_scalars"]
