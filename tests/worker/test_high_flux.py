"""Captures taken at too much flux: first-photon pile-up saturates every return (a histogram then holds only the
leading edge of each view's nearest surface). The end of the run names that as the cause of a bad fit, with what to
do, instead of the time axis or the poses."""

from __future__ import annotations

import numpy as np
import pytest

from spadscan.protocol.pileup import detection_probabilities, saturated_histograms
from spadscan.worker.end_of_run import FitNoise, RunFacts, fit_noise, misfit_warning, warnings


def _ball_capture(path, power: float):
    """6 simulated views of a 0.1 m ball resting on z = 0 from 0.5 m (LCSPCData's simulated sensor) at `power`."""
    import trimesh

    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    mesh.apply_translation([0, 0, 0.1])
    poses = fibonacci_hemisphere(6, 0.5, target=(0, 0, 0.1), min_elevation_deg=10)
    simulate_capture(mesh, sensor_preset("lcspc-sim"), poses, path,
                     settings=SimSettings(rays_per_zone=1024, power=power), seed=1, progress=False)
    return path


@pytest.fixture(scope="module")
def bright_ball(tmp_path_factory):
    return _ball_capture(tmp_path_factory.mktemp("flux") / "bright", 100.0)


@pytest.fixture(scope="module")
def plain_ball(tmp_path_factory):
    return _ball_capture(tmp_path_factory.mktemp("flux") / "plain", 1.0)


def _reconstruct(capture, out):
    from spadscan.worker.reconstruct import reconstruct_capture

    return reconstruct_capture(capture, out, progress=False, device="cpu", threads=1, steps=40,
                               overrides={"mesh_resolution": 32, "early_stop": False})


def test_a_run_on_a_saturated_capture_names_pile_up_and_one_below_it_does_not(bright_ball, plain_ball, tmp_path,
                                                                              one_thread):
    bright = _reconstruct(bright_ball, tmp_path / "bright")
    assert bright["fit_to_noise"]["saturated_histograms"] == bright["fit_to_noise"]["histograms"] > 0
    lines = [w for w in bright["warnings"] if "pile-up" in w]
    assert len(lines) == 1 and "lower the laser power" in lines[0], bright["warnings"]
    assert not any("time axis" in w for w in bright["warnings"]), bright["warnings"]
    plain = _reconstruct(plain_ball, tmp_path / "plain")
    assert plain["fit_to_noise"]["saturated_histograms"] == 0
    assert not any("pile-up" in w for w in plain["warnings"]), plain["warnings"]


def _histograms(signal: float, n: int = 8, cycles: int = 5000) -> np.ndarray:
    """n first-photon histograms (n, 512) of a return at bin 200 carrying `signal` photons a cycle over a background
    of 2.5e-4 a bin (their expected counts)."""
    bins = np.arange(512)
    pulse = np.exp(-0.5 * ((bins - 200) / 2.0) ** 2)
    rate = 2.5e-4 + signal * pulse / pulse.sum()
    return np.tile(detection_probabilities(rate) * cycles, (n, 1))


def test_saturated_histograms_are_told_from_bright_ones_by_the_shadow_behind_their_return():
    valid = np.ones((8, 512), bool)
    assert saturated_histograms(_histograms(100.0), valid).all()
    assert not saturated_histograms(_histograms(1.5), valid).any()
    assert not saturated_histograms(np.zeros((8, 512)), valid).any()  # no background: nothing to judge


def _fit(saturated: int, **kw) -> FitNoise:
    base = dict(deviance_per_bin=1.6, noise_per_bin=0.2, bins=16384, relative_misfit=0.75, histograms=16,
                misfit_histograms=16, excess_z=150.0)
    return FitNoise(**{**base, **kw}, saturated_histograms=saturated)


@pytest.mark.parametrize("measured", [False, True])
def test_a_saturated_capture_that_fits_badly_names_pile_up_and_what_to_do(measured):
    line = misfit_warning(_fit(16), measured)
    assert "saturated (16 of the 16 checked)" in line and "pile-up" in line
    assert "lower the laser power or the exposure, or move the sensor back" in line
    assert "time axis" not in line and "calibration" not in line
    share = misfit_warning(_fit(16, relative_misfit=0.3, misfit_histograms=10), False)
    assert "10 of 16" in share and "pile-up" in share and "part of the surface" not in share


def test_a_capture_with_few_saturated_histograms_keeps_the_other_causes():
    assert "its time axis (the sensor's bin_width_m, zero_bin), its poses or the fit are wrong" in misfit_warning(
        _fit(3), False)
    assert "a wrong sensor model or calibration" in misfit_warning(_fit(3), True)
    assert "pile-up" not in misfit_warning(_fit(8), False)  # half is not most


def test_a_saturated_capture_that_fits_says_so_once():
    fine = _fit(16, relative_misfit=0.05, misfit_histograms=0, excess_z=1.0)
    facts = RunFacts(stopped_by="converged", steps=300, model_converged=True, data_terms=[0.5] * 300, fit=fine,
                     measured=False)
    lines = [line for line in warnings(facts) if "pile-up" in line]
    assert len(lines) == 1 and "comes from the fit's smoothness" in lines[0]
    facts.fit = _fit(16)
    lines = [line for line in warnings(facts) if "pile-up" in line]
    assert len(lines) == 1 and lines[0].startswith("the fit does not explain the measurements")


def test_the_fit_check_counts_the_saturated_histograms():
    measured = _histograms(100.0)[:, None]
    fit = fit_noise(measured, np.maximum(measured, 0.1))
    assert fit.saturated and fit.saturated_histograms == 8 and fit.to_dict()["saturated_histograms"] == 8
    assert fit_noise(_histograms(1.5)[:, None], _histograms(1.5)[:, None] + 0.1).saturated_histograms == 0


def test_a_live_job_says_in_its_status_that_the_views_so_far_are_saturated(bright_ball, tmp_path, one_thread):
    """Said while the scan runs, the power can be lowered before the rest of the scan is taken that way."""
    from live_helpers import ReplayScan
    from test_live_job import LiveJobThread, small_settings

    root = tmp_path / "captures"
    scan = ReplayScan(bright_ball, root / "ball")
    scan.run()
    live = LiveJobThread(root, "ball", small_settings())
    status = live.wait_status(lambda s: s.state == "live", "a live fit")
    assert len(status.warnings) == 1 and status.warnings[0].startswith("the histograms are saturated (6 of the 6 "
                                                                       "read so far)"), status
    assert any(line.startswith("live: warning: the histograms are saturated") for line in live.lines), live.lines
    scan.finish()
    live.join()


def test_the_live_line_counts_the_histograms_with_detections_and_says_nothing_below_saturation(bright_ball,
                                                                                              plain_ball):
    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.worker.live.saturation import live_saturation_warning

    bright = CaptureReader(bright_ball).load().hists
    assert "(6 of the 6 read so far)" in live_saturation_warning(bright)
    empty = np.zeros_like(bright[:4])
    assert "(6 of the 6 read so far)" in live_saturation_warning(np.concatenate([bright, empty]))
    assert live_saturation_warning(CaptureReader(plain_ball).load().hists) is None
    assert live_saturation_warning(empty) is None
