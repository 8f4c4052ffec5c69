"""`keep_the_better` leaves the model holding the field it reports as published: the final field when that one
explains the views better (not the live field it scored last), and never a diverged field, whose non-finite
deviance is no number in report.json."""

from __future__ import annotations

import json

import torch

from spadscan.worker.live.keep import LiveState, keep_the_better, scalars_of, use_field
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.fast.model import make_fast_model
from spadscan.worker.recon.presets import preset_config

from test_live_fit import PLAN, grown_scenes
from worker_helpers import FAST_SMALL


def fitted(scene, steps: int):
    model = make_fast_model(scene, with_overrides(preset_config("fast"), FAST_SMALL), "cpu", PLAN)
    for _ in range(steps):
        model.step()
    return model


def hull_state(model) -> LiveState:
    """A live state that fitted nothing: the model's carved hull, as a field of the model's grid."""
    field = model.mesh_field()
    hull = model.constraint.bound_for(model.field).detach()[0, 0].clone()
    return LiveState(type(field)(field.origin.numpy(), field.voxel, hull), model.level, scalars_of(model))


def test_a_final_field_that_fits_better_is_the_one_the_model_holds(cylinder_capture, tmp_path, one_thread):
    _, every = grown_scenes(cylinder_capture, tmp_path, 16)
    final = fitted(every, 40)
    own = final.mesh_field().sdf.detach().clone()
    kept = keep_the_better(final, hull_state(final), log=lambda line: None)
    assert kept["published"]["mesh"] == "final"
    assert kept["published"]["deviance_final"] < kept["published"]["deviance_live"]
    assert torch.allclose(final.mesh_field().sdf, own, atol=1e-6), "the model holds the live field it scored last"


def test_a_diverged_final_field_loses_and_its_deviance_is_no_number(cylinder_capture, tmp_path, one_thread):
    _, every = grown_scenes(cylinder_capture, tmp_path, 16)
    live = fitted(every, 40)
    field = live.mesh_field()
    state = LiveState(type(field)(field.origin.numpy(), field.voxel, field.sdf.detach()[0, 0].clone()), live.level,
                      scalars_of(live))
    final = fitted(every, 40)
    use_field(final, torch.full_like(final.field.sdf, float("nan")))
    kept = keep_the_better(final, state, log=lambda line: None)
    assert kept["published"]["mesh"] == "live" and kept["published"]["deviance_final"] is None
    assert bool(torch.isfinite(final.mesh_field().sdf).all())
    json.dumps(kept, allow_nan=False)  # report.json stays strict JSON
