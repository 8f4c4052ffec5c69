"""Which mesh a live job publishes: the final run's, or the live fit's it started from, whichever explains the
measurements better.

The final run is short (it polishes the live fit within the job's budget), and a short budget may also coarsen its
mesh. So once it ends, both fields are scored on every view of the complete capture with the same rays (the data
term, deviance per bin: `FastModel.deviance_all_views`): the better one is published, meshed at no fewer cells a
side than the live mesh had. report.json says which (`published`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

SCORE_SEED = 0
"""The rays both fields are scored on."""


def keep_the_better(model, live_field, out: Path, config, live_resolution: int, truth,
                    log: Callable[[str], None]) -> dict:
    """Score the final model's mesh field and `live_field` (a GridField; projected into the final model's hull, as
    at the warm start) on every view; re-mesh `out`/mesh.ply from the live field when it is the better, or from the
    final field when the final run meshed it coarser than the run's `config.mesh_resolution` or the live mesh's
    `live_resolution`. Returns report.json's `published` (and the metric fields of a mesh it rewrote, on
    `config.metrics_points` points against `truth` when there is one)."""
    from ..outputs import export_mesh

    resolution = max(config.mesh_resolution, live_resolution)

    final_values = model.mesh_field().sdf.detach().clone()
    use_field(model, final_values)
    final_dev = model.deviance_all_views(SCORE_SEED)
    model.warm_start(live_field, model.level, model.level_steps)
    live_dev = model.deviance_all_views(SCORE_SEED)
    which = "live" if live_dev < final_dev else "final"
    published = {"mesh": which, "deviance_live": round(live_dev, 5), "deviance_final": round(final_dev, 5)}
    meshed = int(_report_resolution(out))
    if which == "final":
        if meshed >= resolution:
            log(f"live: published the final mesh (deviance per bin {final_dev:.4f} against the live fit's "
                f"{live_dev:.4f})")
            return {"published": published}
        use_field(model, final_values)
    res = max(meshed, resolution)
    mesh = model.extract_mesh(res)
    export_mesh(mesh, Path(out) / "mesh.ply", vertex_normal=True)
    published["mesh_resolution"] = res
    log(f"live: published the {which} mesh at {res} cells a side (deviance per bin: live {live_dev:.4f}, final "
        f"{final_dev:.4f})")
    extra = {"published": published, "mesh_resolution": res}
    if truth is not None:
        extra.update(truth.metrics(mesh, n_points=config.metrics_points).to_dict())
    return extra


def use_field(model, values) -> None:
    """Set the model's grid (and the field it meshes) to `values`, of the grid's own shape."""
    import torch

    with torch.no_grad():
        model.field.sdf.copy_(values)
    model.jumped()


def _report_resolution(out: Path) -> int:
    import json

    try:
        return int(json.loads((Path(out) / "report.json").read_text()).get("mesh_resolution") or 0)
    except (OSError, ValueError):
        return 0


__all__ = ["keep_the_better", "use_field"]
