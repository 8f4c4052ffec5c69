"""Which field a live job's final run meshes: its own, or the live fit's it started from, whichever explains the
measurements better.

The final run is short (it polishes the live fit for a few seconds' steps, or within the job's budget), and it may
end worse than it began. So once it has trained, before its mesh, metrics and pictures, both fields are scored on
the same views of the complete capture with the same rays (the data term, deviance per bin:
`FastModel.deviance_all_views`): every view of a capture of up to 256 views, and of a larger one the 256 views spread
over it that its set-up read (`problem.setup_views`), whose per-bin mean estimates every view's. The model is left
holding the better one: the mesh, the report's pictures, its fit check and its metrics all describe what is
published. report.json says which (`published`).
"""

from __future__ import annotations

from typing import Callable

SCORE_SEED = 0
"""The rays both fields are scored on."""


def keep_the_better(model, live_field, log: Callable[[str], None]) -> dict:
    """Score the final model's mesh field and `live_field` (a GridField; projected into the final model's hull, as
    at the warm start) on the same views (the module docstring), and leave the better one in `model` (its grid and
    the field it meshes). Returns report.json's `published`: which field, and both deviances per bin."""
    final_values = model.mesh_field().sdf.detach().clone()
    use_field(model, final_values)
    final_dev = model.deviance_all_views(SCORE_SEED)
    model.warm_start(live_field, model.level, model.level_steps)
    live_dev = model.deviance_all_views(SCORE_SEED)
    which = "live" if live_dev < final_dev else "final"
    if which == "final":
        use_field(model, final_values)
    log(f"live: publishing the {which} field (deviance per bin: live {live_dev:.4f}, final {final_dev:.4f})")
    return {"published": {"mesh": which, "deviance_live": round(live_dev, 5), "deviance_final": round(final_dev, 5)}}


def use_field(model, values) -> None:
    """Set the model's grid (and the field it meshes) to `values`, of the grid's own shape."""
    import torch

    with torch.no_grad():
        model.field.sdf.copy_(values)
    model.jumped()


__all__ = ["keep_the_better", "use_field"]
