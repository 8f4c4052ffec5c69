"""`--set KEY=VALUE` refuses every value out of a field's range with one message that states the range: the generic
rules (a number of the field's type, finite, not negative where the preset's value is positive) defer to the
preset's own check of the field wherever it has one, whichever rule catches the value first."""

from __future__ import annotations

import math

import pytest

from spadscan.protocol.errors import SpadscanError
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.presets import preset_config

NAN, INF = math.nan, math.inf


def refusal(preset: str, overrides: dict) -> str:
    with pytest.raises(SpadscanError) as exc:
        with_overrides(preset_config(preset), overrides)
    return str(exc.value)


@pytest.mark.parametrize("value, message", [
    (-4, "field.resolution -4 must be an integer in [4, 1024]"),  # the generic >= 0 rule used to say ">= 0"
    (0, "field.resolution 0 must be an integer in [4, 1024]"),
    (1e9, "field.resolution 1000000000.0 must be an integer in [4, 1024]"),  # the type rule: "does not fit"
])
def test_the_resolution_is_refused_with_its_range_whatever_rule_catches_it(value, message):
    assert refusal("fast", {"field.resolution": value}) == message


# (preset, key, the range its every refusal states, values out of it: caught by the generic rules and by the check)
FIELDS = [
    ("fast", "field.resolution", "must be an integer in [4, 1024]", [-4, 0, 1, 2000, 1e9, 64.5, NAN, INF, True, "x"]),
    ("fast", "field.hull_resolution", "must be an integer in [4, 1024]", [-1, 3, 1e9, False]),
    ("fast", "mesh_resolution", "must be in [8, 1024] cells", [-4, 0, 2000, 1e9, 1000.0, NAN, "x"]),
    ("fast", "field.carve_margin_m", "must be in [0, 1] metres", [-0.5, 2, NAN, INF, -INF, True]),
    ("fast", "schedule.segment_pad_voxels", "must be in [0, 64] voxels", [-1, 65, NAN, INF, True]),
    ("fast", "field.sharpness_voxels", "must be > 0 (0: no opacity anywhere)", [-4, 0, NAN, INF, True]),
    ("fast", "schedule.views_per_step", "must be an integer >= 1", [-1, 0, 2.5, 1e9, True]),
    ("fast", "parts.blur.passes", "must be an integer >= 1", [-1, 0, 2.5, True]),
    ("fast", "parts.unseen.alpha", "must be in (0, 1]", [-1, 0, 2, NAN, INF]),
    ("fast", "parts.unseen.after_steps", "must be an integer >= 0", [-1, 2.5, True]),
    ("fast", "parts.openings.min_hits", "min_hits must be >= 1", [-1, 0, 2.5, INF]),
    ("fast", "parts.erosion.every_steps", "must be >= 1", [-1, 0, 2.5, 1e9]),
    ("fast", "parts.openings.enabled", "must be true or false", [0, 1, -1, "yes", NAN]),
    ("paper", "rays.samples_per_ray", "must be an integer >= 2", [-1, 0, 1, 3.5, True]),
    ("paper", "optim.lr_floor", "must be in [0, 1]", [-0.5, 2, NAN, INF]),
    ("paper", "sharpness.init", "must be > 0", [-1, 0, NAN, INF]),
    ("paper", "sharpness.max", "must be >= sharpness.min 1.0", [-1, 0, 0.5, NAN, INF]),
    # No check of their own: the generic rules are the whole range, and say so every time.
    ("fast", "schedule.fine_steps", "must be an integer >= 0 (the preset's value is 1200)",
     [-1, 2.5, 1e9, NAN, True, "x"]),
    ("fast", "field.box_pad_voxels", "must be a finite number >= 0 (the preset's value is 3.0)",
     [-1, NAN, INF, True, "x"]),
    ("fast", "early_stop", "must be true or false (the preset's value is True)", [0, 1, "yes"]),
    ("paper", "field.weight_norm", "must be true or false (the preset's value is True)", [0, NAN]),
]


@pytest.mark.parametrize("preset, key, rule, values", FIELDS, ids=[f"{p}-{k}" for p, k, _, _ in FIELDS])
def test_every_value_out_of_a_fields_range_gets_one_message_with_that_range(preset, key, rule, values):
    for value in values:
        message = refusal(preset, {key: value})
        assert rule in message and "\n" not in message, (value, message)
        assert key.rpartition(".")[2] in message, (value, message)  # a check may name a section's fields together
        assert ">= 0 (the preset" not in message.replace(rule, ""), (value, message)


@pytest.mark.parametrize("overrides, message", [
    # An earlier override the check refuses first: the field's range is still its own.
    ({"mesh_resolution": 4, "field.resolution": -4}, "field.resolution -4 must be an integer in [4, 1024]"),
    # A range that follows another field takes the value that field was given.
    ({"field.resolution": 128, "schedule.segment_pad_voxels": -1},
     "schedule.segment_pad_voxels -1 must be in [0, 128] voxels (at most field.resolution)"),
    ({"parts.openings.keep_ratio": -1}, "parts.openings.flag_ratio 0.6 and keep_ratio -1 must satisfy 0 < flag_ratio "
                                        "<= keep_ratio"),
])
def test_the_range_stated_is_the_one_of_the_config_being_made(overrides, message):
    assert refusal("fast", overrides) == message


def test_values_the_check_lets_through_name_the_rule_they_break_and_the_range():
    """inf passes a check that asks for > 0, 3.5 one that asks for >= 1: the message says what is wrong with them
    and the same range as every other refusal of the field."""
    assert refusal("fast", {"field.sharpness_voxels": INF}) == ("field.sharpness_voxels inf must be a finite number, "
                                                                 "and must be > 0 (0: no opacity anywhere)")
    assert refusal("fast", {"mesh_resolution": 1000.0}) == ("mesh_resolution 1000.0 must be an integer, and must be in "
                                                            "[8, 1024] cells")
    assert refusal("fast", {"parts.unseen.after_steps": True}) == ("parts.unseen.after_steps True must be an integer "
                                                                   ">= 0")


def test_values_in_range_still_pass_and_are_stored_in_the_fields_type():
    config = with_overrides(preset_config("fast"), {"field.resolution": 48, "field.carve_margin_m": 0,
                                                    "parts.openings.depths_m": [0.05], "early_stop": False,
                                                    "schedule.fine_steps": 0, "field.floor_z": -0.5})
    assert config.field.resolution == 48 and config.field.carve_margin_m == 0.0
    assert isinstance(config.field.carve_margin_m, float) and config.parts.openings.depths_m == (0.05,)
    assert config.early_stop is False and config.schedule.fine_steps == 0 and config.field.floor_z == -0.5


def test_an_integer_too_large_for_a_float_is_refused_in_one_line():
    assert refusal("fast", {"field.box_pad_voxels": 10 ** 400}) == (
        f"config override 'field.box_pad_voxels': {10 ** 400!r} must be a finite number >= 0 (the preset's value is "
        f"3.0)")
    assert refusal("fast", {"field.carve_margin_m": 10 ** 400}) == (f"field.carve_margin_m {10 ** 400!r} must be in "
                                                                    f"[0, 1] metres")
