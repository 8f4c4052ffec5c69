"""Ambient light that stops the laser cycles before the object's returns: the share it stops follows Coates' law, a
capture under bright light says so at the end of its run, and one under the sensor's own light says nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.scenes import builtin_scene
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker.ambient_light import STOPPED_LIMIT, Ambient, ambient_warning, capture_ambient
from spadscan.worker.end_of_run import RunFacts, warnings


def test_the_share_stopped_is_coates_at_the_median_return():
    """exp(-b r) of the cycles are live at bin r: the share stopped is its complement, at the median return's bin and
    the median histogram's rate; photons per bin count each view's cycles."""
    background = np.full((4, 2), 1e-3)
    background[3, 0] = 1.0  # one bright histogram does not move the median
    cycles = np.array([5000.0, 5000.0, 10000.0, 10000.0])
    ambient = capture_ambient(background, cycles, np.array([100.0, 300.0, 500.0, np.nan]), pileup=True)
    assert ambient.return_bin == 300.0 and ambient.returns == 3
    assert ambient.stopped_share == pytest.approx(1 - math.exp(-0.3))
    assert ambient.background_photons == pytest.approx(7.5)  # median of 5 and 10 photons per bin


def test_nothing_is_judged_without_pile_up_returns_or_data():
    background = np.full((3, 1), 0.01)
    assert capture_ambient(background, np.ones(3), np.array([400.0]), pileup=False) is None
    assert capture_ambient(background, np.ones(3), np.array([]), pileup=True) is None
    assert capture_ambient(background, np.ones(3), np.array([400.0]), pileup=True,
                           usable=np.zeros((3, 1), bool)) is None
    usable = np.array([[True], [False], [False]])
    background[1:] = 1.0  # histograms without data do not count
    assert capture_ambient(background, np.ones(3), np.array([10.0]), True, usable).background == 0.01


def test_the_warning_says_the_share_and_what_to_do():
    dim = Ambient(background=2.5e-4, background_photons=1.2, return_bin=330, stopped_share=0.08, returns=256)
    bright = Ambient(background=2e-3, background_photons=10.0, return_bin=340, stopped_share=0.49, returns=256)
    assert ambient_warning(dim) is None and ambient_warning(None) is None
    line = ambient_warning(bright)
    assert line.startswith("too much ambient light: it stopped 49 % of the laser cycles") and "2.0x fainter" in line
    assert "darken the room" in line
    blinding = ambient_warning(Ambient(background=1.0, background_photons=5000.0, return_bin=300, stopped_share=1.0,
                                       returns=256))  # light that stops every cycle: the figure stays finite
    assert "over 1,000x fainter" in blinding and "inf" not in blinding, blinding
    stopped = capture_ambient(np.full((2, 1), 1e3), np.ones(2), np.array([1e6]), pileup=True)
    assert stopped.stopped_share == 1.0 and math.isfinite(stopped.background_photons)
    facts = RunFacts(stopped_by="converged", steps=100, model_converged=True, data_terms=[1.0] * 100, ambient=bright)
    assert warnings(facts) == [line]
    assert 0.08 < STOPPED_LIMIT < 0.49


@pytest.mark.usefixtures("one_thread")
def test_reconstruct_warns_of_a_capture_under_bright_light(tmp_path):
    """The same sphere under ten times the lcspc-sim's ambient light says so; under its own light it does not. The
    report keeps the figures."""
    from spadscan.worker.reconstruct import reconstruct_capture

    poses = fibonacci_hemisphere(24, 0.5, target=(0, 0, 0.05))
    reports = {}
    for name, ambient in (("room", None), ("bright", 2.5e-3)):
        simulate_capture(builtin_scene("sphere"), sensor_preset("lcspc-sim"), poses, tmp_path / name,
                         settings=SimSettings(rays_per_zone=256, ambient=ambient), progress=False)
        reports[name] = reconstruct_capture(tmp_path / name, tmp_path / f"{name}-out", steps=5, progress=False,
                                            device="cpu", threads=1,
                                            overrides={"mesh_resolution": 48, "early_stop": False})
    said = [w for w in reports["bright"]["warnings"] if w.startswith("too much ambient light")]
    assert len(said) == 1, reports["bright"]["warnings"]
    assert reports["bright"]["ambient_light"]["stopped_share"] > STOPPED_LIMIT
    assert reports["room"]["ambient_light"]["stopped_share"] < STOPPED_LIMIT
    assert not any("ambient" in w for w in reports["room"]["warnings"]), reports["room"]["warnings"]
