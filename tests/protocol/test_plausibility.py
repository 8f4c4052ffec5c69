"""Histograms no sensor could produce (saturated, above the counter, all zero, all equal, more counts than a
first-photon sensor's cycles allow): a capture made only of
them is refused in one line, one that holds some is warned about in one line, and real and simulated captures pass
without a word."""

from __future__ import annotations

import numpy as np
import pytest

from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_reader import CaptureReader, check_capture_counts
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.plausibility import (CYCLES_MARGIN, UINT32_MAX, check_counts, first_photon_cycles,
                                            implausible, survey_counts)
from spadscan.protocol.sensor_presets import sensor_preset

TMF_LIMIT = 2**24 - 1


def noise(shape, mean=120.0, seed=0) -> np.ndarray:
    """Background counts as a sensor sees them (Poisson)."""
    return np.random.default_rng(seed).poisson(mean, shape).astype(np.uint32)


def write(path, sensor, hists):
    w = CaptureWriter.create(path, sensor, chunk_size=8)
    for i, h in enumerate(hists):
        w.append(Measurement(h, np.eye(4), i))
    w.finish("complete")
    return path


def one_line_refusal(hists, max_count=UINT32_MAX, ignore_bins=(), cycles=None) -> str:
    with pytest.raises(CaptureError) as info:
        check_counts(hists, max_count, ignore_bins, "cap", cycles)
    message = str(info.value)
    assert "\n" not in message and message.startswith("cap: no sensor could have produced these counts: ")
    return message


def test_a_capture_whose_every_count_is_the_uint32_maximum_is_refused():
    """The fault as found: every count 2**32-1. On a 32-bit sensor that is saturation; on the TMF8820, counts its
    24-bit counter cannot hold."""
    hists = np.full((4, 1, 1024), UINT32_MAX, np.uint32)
    assert "all 4 histograms are saturated (every bin at the 32-bit counter's limit 4,294,967,295)" in \
        one_line_refusal(hists)
    tmf = np.full((4, 9, 128), UINT32_MAX, np.uint32)
    assert "all 36 histograms hold counts above the 24-bit counter's limit 16,777,215" in \
        one_line_refusal(tmf, TMF_LIMIT, (0,))


@pytest.mark.parametrize("kind, make, words", [
    ("saturated at a 24-bit counter", lambda h: h.fill(TMF_LIMIT), "are saturated (every bin at the 24-bit"),
    ("above a 24-bit counter", lambda h: h.__setitem__((..., 50), TMF_LIMIT + 1), "hold counts above the 24-bit"),
    ("all zero", lambda h: h.fill(0), "are all zero"),
    ("all equal", lambda h: h.fill(100), "have every bin equal"),
])
def test_each_kind_alone_is_refused_and_in_part_warned_about(kind, make, words):
    hists = noise((6, 9, 128))
    make(hists)
    assert words in one_line_refusal(hists, TMF_LIMIT, (0,))
    some = noise((6, 9, 128))
    part = some[:2, :3]
    make(part)
    some[:2, :3] = part
    warning = check_counts(some, TMF_LIMIT, (0,), "cap")
    assert warning.startswith("cap: 6 of 54 histograms no sensor could have produced (6 ") and "\n" not in warning


def test_the_ignored_bins_do_not_make_a_histogram_plausible():
    """The TMF8820's bin 0 holds what it likes: a histogram flat everywhere else is still flat."""
    hists = np.full((3, 9, 128), 100, np.uint32)
    hists[..., 0] = np.arange(27).reshape(3, 9)
    assert "have every bin equal" in one_line_refusal(hists, TMF_LIMIT, (0,))


def test_a_mix_of_kinds_is_refused_with_each_named():
    hists = np.zeros((2, 1, 64), np.uint32)
    hists[1] = UINT32_MAX
    assert one_line_refusal(hists).endswith(
        "of its 2 histograms, 1 saturated (every bin at the 32-bit counter's limit 4,294,967,295), 1 all zero; "
        "refusing to fit them")


def test_clipped_bins_in_plausible_histograms_are_warned_about():
    hists = noise((4, 9, 128))
    hists[1, 4, 30] = TMF_LIMIT
    survey = survey_counts(hists, TMF_LIMIT, (0,))
    assert (survey.n_implausible, survey.clipped) == (0, 1)
    assert check_counts(hists, TMF_LIMIT, (0,), "cap") == \
        "cap: 1 of 36 histograms with bins clipped at the counter's limit 16,777,215"


def test_sensor_like_counts_pass_silently():
    assert check_counts(noise((8, 9, 128)), TMF_LIMIT, (0,), "cap") is None
    sparse = noise((8, 1, 1024), mean=1.2)  # LCSPCData's simulated background: about one count a bin
    assert check_counts(sparse, UINT32_MAX, (), "cap") is None


def test_more_counts_than_a_first_photon_sensors_cycles_allow_are_implausible():
    """A sensor that stops at its first photon counts at most one a laser cycle. One bin raised to 50,000 in a
    5,000-cycle histogram (about 3,000 counts before) pulled a fit's albedo down and spoiled its fit of the others."""
    cycles = first_photon_cycles(sensor_preset("lcspc-sim"))
    assert cycles == 5000
    hists = noise((24, 1, 1024), mean=3.0)  # about 3,000 counts of 5,000 cycles, as the simulated sphere's
    hists[5, 0, 500] = 50_000
    assert check_counts(hists, UINT32_MAX, (), "cap", cycles) == (
        "cap: 1 of 24 histograms no sensor could have produced (1 with more counts than 1.5 x their 5,000 laser "
        "cycles), left out")
    assert np.flatnonzero(implausible(hists, UINT32_MAX, (), cycles)).tolist() == [5]
    assert check_counts(hists, UINT32_MAX, (), "cap") is None, "no bound without a first-photon sensor's cycles"
    hists[:, 0, 500] = 50_000
    assert "all 24 histograms hold more counts than 1.5 x their 5,000 laser cycles (a sensor that stops at its " \
        "first photon counts at most one a cycle)" in one_line_refusal(hists, UINT32_MAX, (), cycles)


def test_the_cycles_bound_has_a_margin_and_counts_only_the_bins_tested():
    """Up to CYCLES_MARGIN x the cycles is let through (the TMF8820's 4 million cycles are an estimate, +-0.7
    million a frame); the ignored bin 0 and bins clipped at the counter are not summed."""
    tmf = sensor_preset("tmf8820")
    cycles = first_photon_cycles(tmf)
    assert cycles == 4_000_000 and first_photon_cycles(tmf.with_(pileup=False)) is None
    hists = noise((2, 9, 128)).astype(np.uint32)
    bound = int(CYCLES_MARGIN * cycles)
    hists[0, 0, 40] += bound - int(hists[0, 0, 1:].sum())  # exactly at the bound: plausible
    hists[1, 0, 40] += bound + 1 - int(hists[1, 0, 1:].sum())  # one count over it
    assert implausible(hists, TMF_LIMIT, (0,), cycles)[:, 0].tolist() == [False, True]
    hists[1, 0, 40] -= 2
    hists[1, 0, 0] = TMF_LIMIT - 1  # bin 0 reads what it likes
    hists[1, 1, 30:40] = TMF_LIMIT  # ten bins clipped: told as clipped, not as over the cycles
    survey = survey_counts(hists, TMF_LIMIT, (0,), cycles)
    assert (survey.n_implausible, survey.clipped) == (0, 1)


def test_the_checks_of_a_capture_folder_name_it(tmp_path):
    sensor = sensor_preset("tmf8820")
    bad = write(tmp_path / "bad", sensor, np.full((3, 9, 128), UINT32_MAX, np.uint32))
    with pytest.raises(CaptureError, match=f"^{bad}: no sensor could have produced these counts"):
        check_capture_counts(bad)
    hists = noise((3, 9, 128))
    hists[0] = 0
    some = write(tmp_path / "some", sensor, hists)
    warned = []
    note = check_capture_counts(some, warned.append)
    assert note == f"{some}: 9 of 27 histograms no sensor could have produced (9 all zero), left out"
    assert warned == [f"warning: {note}"]
    assert CaptureReader(bad).load().hists.max() == UINT32_MAX, "reading a capture does not refuse it"


def test_simulated_captures_pass(tmp_path):
    from spadscan.protocol.scenes import builtin_scene
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    poses = fibonacci_hemisphere(6, 0.3, target=(0, 0, 0.03), min_elevation_deg=10)
    for preset in ("tmf8820", "lcspc-sim"):
        path = tmp_path / preset
        simulate_capture(builtin_scene("sphere"), sensor_preset(preset), poses, path,
                         settings=SimSettings(rays_per_zone=16), seed=1, progress=False)
        assert check_capture_counts(path) is None, preset
        assert survey_on_cycles(path).n_implausible == 0, preset


def survey_on_cycles(path):
    """`survey_counts` of a capture folder with its sensor's first-photon cycles bound."""
    data = CaptureReader(path).load()
    sensor = data.sensor
    return survey_counts(data.hists, sensor.max_count, sensor.ignore_bins, first_photon_cycles(sensor))


@pytest.mark.dataset
@pytest.mark.parametrize("rel", ["real/pyramid/pyramid.json", "real/pyramid/pyramid_random.json",
                                 "simulated/sphere/sphere.json", "simulated/bunny/bunny.json",
                                 "simulated/soap/soap.json"])
def test_the_datasets_captures_pass(lcspc_dataset, tmp_path, rel):
    """LCSPCData's real TMF8820 captures (ambient ~120 counts a bin, peaks under 10**6) and its simulated ones. Each
    histogram also holds fewer counts than its sensor model's cycles (the real ones at most 0.43 of the TMF8820's 4
    million, the simulated ones 0.96 of their 5,000): the first-photon bound flags none."""
    from spadscan.protocol.lcspc import import_lcspc

    import_lcspc(lcspc_dataset / rel, tmp_path / "cap")
    assert check_capture_counts(tmp_path / "cap") is None
    survey = survey_on_cycles(tmp_path / "cap")
    assert survey.n_implausible == 0 and survey.cycles is not None
    data = CaptureReader(tmp_path / "cap").load()
    kept = [b for b in range(data.sensor.n_bins) if b not in data.sensor.ignore_bins]
    assert data.hists[..., kept].sum(axis=-1, dtype=np.int64).max() < data.sensor.cycles
