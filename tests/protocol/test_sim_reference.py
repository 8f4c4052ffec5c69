"""The simulated reference histogram: the real TMF8820's reference shape, from which the measured-data path derives
the sensor model's pulse (docs/sensor_models.md)."""

import numpy as np
import pytest

from spadscan.protocol.scenes import builtin_scene
from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, Simulator
from spadscan.worker.pulse import pulse_kernel

TMF = sensor_preset("tmf8820")


def mean_delay_and_tail(kernel, origin):
    """(mean delay after the arrival, share of the pulse 4 or more bins after it), bins."""
    t = np.arange(len(kernel)) - origin
    return float((kernel * t).sum()), float(kernel[t >= 4].sum())


@pytest.fixture(scope="module")
def references():
    frames = Simulator(builtin_scene("pyramid"), TMF, seed=0).frames(fibonacci_hemisphere(16, 0.4))
    return frames.reference.astype(float)


def test_a_pulse_derived_from_a_simulated_reference_is_the_sensor_models(references):
    """The reference used to be the zones' pulse itself: the pulse derived from it came 0.68 bins early, with a
    third of the tail (what the worker fits a capture marked real with)."""
    derived, origin, source = pulse_kernel(TMF, references.mean(axis=0))
    preset, preset_origin, preset_source = pulse_kernel(TMF, None)
    assert source == "reference" and preset_source == "sensor model"
    delay, tail = mean_delay_and_tail(derived, origin)
    preset_delay, preset_tail = mean_delay_and_tail(preset, preset_origin)
    assert delay == pytest.approx(preset_delay, abs=0.1)
    assert tail == pytest.approx(preset_tail, abs=0.02)


def test_the_reference_peaks_where_the_real_ones_do_with_their_counts(references):
    mean = references.mean(axis=0)
    assert int(mean.argmax()) == 14  # the real TMF8820's reference peaks at bin index 14.27
    assert mean.sum() == pytest.approx(0.06 * TMF.cycles, rel=0.01)  # ~2.4e5 counts over 4e6 cycles
    assert np.median(mean[60:]) == pytest.approx(4.0, abs=1.0)  # its floor: ~4 counts per bin
    # wider in its tail than the zones' pulse (the mapping's power 1.5): a fifth of the signal 6 bins after the peak
    signal = np.clip(mean - 4.0, 0, None)
    assert 0.15 < signal[20:].sum() / signal.sum() < 0.25


def test_the_shape_is_the_mapping_run_backwards():
    from spadscan.protocol.simulator import reference_shape

    kernel, origin = TMF.pulse.kernel(1)
    shape = reference_shape(kernel, origin, 128, 14.27)
    assert shape.sum() == pytest.approx(1.0) and int(shape.argmax()) == 14
    # at a bin index u the shape is p(1.10 (u - 14.27)) ** (1 / 1.5), relative to its value at the peak
    u = np.array([16, 20, 30])
    p = np.interp(1.10 * (u - 14.27), np.arange(kernel.size) - origin, kernel / kernel.max())
    peak = np.interp(1.10 * (14 - 14.27), np.arange(kernel.size) - origin, kernel / kernel.max())
    np.testing.assert_allclose(shape[u] / shape[14], (p / peak) ** (1 / 1.5), rtol=1e-12)


def test_the_zones_counts_do_not_depend_on_the_reference():
    """The reference draws from its own generator: changing it leaves every later frame's counts as they were."""
    poses = fibonacci_hemisphere(4, 0.4)
    a = Simulator(builtin_scene("pyramid"), TMF, seed=3)
    b = Simulator(builtin_scene("pyramid"), TMF, SimSettings(reference_signal=0.2), seed=3)
    for _ in range(2):
        fa, fb = a.frames(poses), b.frames(poses)
        np.testing.assert_array_equal(fa.hists, fb.hists)
    assert fb.reference.sum() > 3 * fa.reference.sum()
