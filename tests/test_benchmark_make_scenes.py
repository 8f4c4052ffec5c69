"""benchmarks/make_scenes.py: which scenes each group makes, and how."""

from __future__ import annotations

from spadscan.protocol.scenes import SPLITS

from benchmark_helpers import load_benchmark


def test_the_tuning_group_is_the_tuning_splits_builtins_but_the_large_ones():
    """The tuning group makes every built-in the method is tuned on in the validation format, the dish among them; the
    large ones stay their own group, and no scene of another split slips in."""
    make_scenes = load_benchmark("make_scenes")
    tuning = dict(make_scenes.plans(["tuning"], 3))
    builtins = {s.split(":", 1)[1] for s in SPLITS["tuning"] if s.startswith("builtin:")}
    assert set(tuning) == builtins - set(make_scenes.LARGE_SCENES) and "dish" in tuning
    assert tuning["dish"] == ["builtin:dish", *make_scenes.VALIDATION_OPTIONS, "--seed", "3"]
    assert not set(tuning) & {name for name, _ in make_scenes.plans(["validation", "holdout", "check", "large"], 3)}


def test_the_aimed_group_is_the_validation_split_aimed_at_each_objects_mid_height():
    """Every validation scene once more, its views aimed at half its height instead of the floor under it, under a
    name of its own."""
    from spadscan.protocol.scenes import builtin_scene

    make_scenes = load_benchmark("make_scenes")
    aimed = dict(make_scenes.plans(["aimed"], 2))
    validation = dict(make_scenes.plans(["validation"], 2))
    assert set(aimed) == {f"{name}-mid" for name in validation}
    for name, args in validation.items():
        target = aimed[f"{name}-mid"][aimed[f"{name}-mid"].index("--target") + 1:][:3]
        height = float(builtin_scene(name).bounds[1, 2])
        assert target[:2] == ["0", "0"] and float(target[2]) == round(height / 2, 3) > 0.02
        assert [a for a in aimed[f"{name}-mid"] if a not in ("--target", *target)] == args
