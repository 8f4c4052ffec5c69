"""A run whose training overran its time budget (or whose set-up used it all) is advised only what would make its
steps faster where it ran: --device cuda only where torch sees a CUDA device (else a machine with a GPU), none on a
run already on one, and the fast preset only to a run of a slower preset."""

from __future__ import annotations

import pytest

from spadscan.protocol.mesh_io import load_mesh_spec
from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker import end_of_run, reconstruct
from spadscan.worker.end_of_run import RunFacts, faster_ways, warnings

from worker_helpers import FAST_SMALL


def overrun(preset: str, device: str, cuda_seen: bool) -> str:
    """The over-budget line of a run whose one step took 82 s of the 2.8 s its 40 s budget left training."""
    facts = RunFacts("budget", 1, None, [1.0], device=device, cpu_seconds=80.0, wall_seconds=81.8, budget_s=40.0,
                     elapsed_s=159.0, training_s=81.8, training_budget_s=2.8, preset=preset, cuda_seen=cuda_seen)
    (line,) = [w for w in warnings(facts) if w.startswith("the run took")]
    return line


@pytest.mark.parametrize("preset, device, cuda_seen, advice", [
    ("fast", "cpu", False, "a time budget of many steps or a machine with a GPU"),
    ("fast", "cpu", True, "a time budget of many steps or a faster device (--device cuda)"),
    ("paper", "cpu", False, "a time budget of many steps, a machine with a GPU or the fast preset (--preset fast)"),
    ("paper", "cpu", True,
     "a time budget of many steps, a faster device (--device cuda) or the fast preset (--preset fast)"),
    ("paper", "cuda", True, "a time budget of many steps or the fast preset (--preset fast)"),
    ("fast", "cuda", True, "a time budget of many steps"),
])
def test_an_overrun_is_advised_only_what_applies(preset, device, cuda_seen, advice):
    line = overrun(preset, device, cuda_seen)
    assert line.endswith(f"and a run takes at least one; give it {advice}"), line


def test_a_run_whose_facts_do_not_say_is_advised_both_as_they_may_apply():
    assert faster_ways(None, "cpu", None) == ["a faster device (--device cuda)", "the fast preset (--preset fast)"]


@pytest.mark.parametrize("cuda_seen, advice", [
    (False, "a larger time budget or a machine with a GPU"),
    (True, "a larger time budget or a faster device (--device cuda)"),
])
def test_a_set_up_that_used_the_budget_is_advised_only_what_applies(monkeypatch, cuda_seen, advice):
    monkeypatch.setattr(reconstruct.torch.cuda, "is_available", lambda: cuda_seen)
    line = reconstruct._spent_at_set_up(45.0, 40.0, "fast", "cpu")
    assert line.endswith(f"and the run will end late; give it {advice}"), line
    assert "preset (" not in line, "the fast preset has none faster"


def test_a_run_tells_its_checks_its_preset_and_whether_torch_sees_a_gpu(tmp_path, monkeypatch):
    """What the advice reads is what ran: a two-step run of the fast preset, on a machine without a GPU."""
    poses = fibonacci_hemisphere(6, 0.3, target=(0, 0, 0.05), min_elevation_deg=15)
    mesh = load_mesh_spec("builtin:sphere")[0]
    capture = simulate_capture(mesh, sensor_preset("lcspc-sim"), poses, tmp_path / "cap",
                               settings=SimSettings(rays_per_zone=64), progress=False)
    seen: list[RunFacts] = []
    judge = end_of_run.warnings
    monkeypatch.setattr(end_of_run, "warnings", lambda facts: seen.append(facts) or judge(facts))
    monkeypatch.setattr(reconstruct.torch.cuda, "is_available", lambda: False)
    reconstruct.reconstruct_capture(capture, tmp_path / "out", preset="fast", steps=2, device="cpu",
                                    overrides=FAST_SMALL, progress=False)
    (facts,) = seen
    assert (facts.preset, facts.device, facts.cuda_seen) == ("fast", "cpu", False)
