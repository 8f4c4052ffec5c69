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
