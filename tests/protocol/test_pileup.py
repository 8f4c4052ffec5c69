"""Coates pile-up: the forward probabilities against the product formula, the inverse, and extreme rates."""

import numpy as np
import pytest

from spadscan.protocol import pileup
from spadscan.protocol.errors import SimulationError


def direct_probabilities(rate):
    """p_b = (1 - exp(-l_b)) * prod_{j<b} exp(-l_j), written out bin by bin (the textbook form)."""
    p, survive = [], 1.0
    for lam in rate:
        p.append((1 - np.exp(-lam)) * survive)
        survive *= np.exp(-lam)
    return np.array(p)


def test_matches_product_formula_and_conserves_cycles():
    rate = np.random.default_rng(1).uniform(0, 0.05, size=64)
    p = pileup.detection_probabilities(rate)
    np.testing.assert_allclose(p, direct_probabilities(rate), rtol=1e-12)
    # every cycle either detects in exactly one bin or misses
    assert p.sum() + pileup.miss_probability(rate) == pytest.approx(1.0, abs=1e-14)


def test_batches_along_leading_axes():
    rate = np.random.default_rng(2).uniform(0, 0.1, size=(3, 2, 16))
    p = pileup.detection_probabilities(rate)
    assert p.shape == rate.shape
    np.testing.assert_allclose(p[1, 1], direct_probabilities(rate[1, 1]), rtol=1e-12)


def test_high_flux_skews_the_peak_earlier_and_suppresses_later_bins():
    t = np.arange(200)
    shape = np.exp(-0.5 * ((t - 100) / 5.0) ** 2)
    peaks, means = [], []
    for amp in (1e-3, 0.1, 1.0, 10.0):
        p = pileup.detection_probabilities(1e-4 + amp * shape)
        peaks.append(int(p.argmax()))
        means.append(float((t * p).sum() / p.sum()))
    assert peaks[0] == 100  # low flux: the histogram is the rate
    assert all(a >= b for a, b in zip(peaks, peaks[1:])) and peaks[-1] < 95
    assert all(a > b for a, b in zip(means, means[1:]))
    # behind a strong return the background is suppressed by exactly the fraction of cycles already used up
    p = pileup.detection_probabilities(1e-4 + 1.0 * shape)
    live_after = np.exp(-(1e-4 + shape)[:150].sum())
    assert p[170] / (1 - np.exp(-1e-4)) == pytest.approx(live_after * np.exp(-1e-4 * 20), rel=1e-9)


def test_coates_inverts_expected_counts():
    rate = 1e-3 + 0.3 * np.exp(-0.5 * ((np.arange(100) - 40) / 3.0) ** 2)
    cycles = 10_000
    counts = cycles * pileup.detection_probabilities(rate)
    np.testing.assert_allclose(pileup.coates_correct(counts, cycles), rate, rtol=1e-9)
    # one cycle count per histogram, broadcast over leading axes
    both = pileup.coates_correct(np.stack([counts, 2 * counts]), np.array([cycles, 2 * cycles]))
    np.testing.assert_allclose(both, np.stack([rate, rate]), rtol=1e-9)


def test_coates_recovers_rates_from_drawn_counts():
    rng = np.random.default_rng(3)
    rate = np.full(50, 0.02)
    cycles = 200_000
    p = pileup.detection_probabilities(rate)
    counts = rng.multinomial(cycles, np.append(p, 1 - p.sum()))[:-1]
    est = pileup.coates_correct(counts, cycles)
    assert abs(est.mean() / 0.02 - 1) < 0.02  # the raw counts read ~40% low at the end; the estimate does not
    assert counts[-5:].mean() / cycles < 0.7 * 0.02


def test_extreme_rates_stay_finite():
    rate = np.array([0.0, 0.0, 1e-300, 1e6, 1e300, 0.0, 5.0])
    p = pileup.detection_probabilities(rate)
    assert np.all(np.isfinite(p)) and np.all(p >= 0)
    assert p[:3].sum() < 1e-299 and p[3] == pytest.approx(1.0) and p[4:].sum() == 0.0
    assert pileup.miss_probability(np.zeros(4)) == 1.0
    assert pileup.miss_probability(np.full(4, 1e308)) == 0.0


def test_coates_is_finite_when_a_bin_takes_every_cycle():
    counts = np.array([0, 10, 90, 0, 0])  # all 100 cycles end by bin 2
    est = pileup.coates_correct(counts, 100)
    assert np.all(np.isfinite(est))
    assert est[2] == pytest.approx(np.log(90 / 0.5))
    assert np.all(est[3:] == 0)  # no live cycles left: no information, no rate
    over = pileup.coates_correct(np.array([80, 80, 5]), 100)  # more counts than cycles: still finite
    assert np.all(np.isfinite(over))


def test_bad_inputs_raise_one_line_errors():
    with pytest.raises(SimulationError, match="finite"):
        pileup.detection_probabilities(np.array([0.1, np.nan]))
    with pytest.raises(SimulationError, match=">= 0"):
        pileup.detection_probabilities(np.array([-0.1]))
    with pytest.raises(SimulationError, match="cycles"):
        pileup.coates_correct(np.ones(3), 0)
    with pytest.raises(SimulationError, match="counts"):
        pileup.coates_correct(np.array([-1.0, 2.0]), 10)


def test_jitter_blur_spreads_but_keeps_mass_inside():
    p = np.zeros(64)
    p[32] = 0.5
    out = pileup.jitter_blur(p, 2.0)
    assert out.sum() == pytest.approx(0.5, rel=1e-9)
    assert out[32] < 0.25 and (np.arange(64) * out).sum() / out.sum() == pytest.approx(32, abs=1e-9)
    np.testing.assert_array_equal(pileup.jitter_blur(p, 0.0), p)
    edge = np.zeros(64)
    edge[0] = 1.0
    assert pileup.jitter_blur(edge, 2.0).sum() < 0.6  # blurred past bin 0: detected outside the window


def test_saturation_is_read_from_the_shadow_behind_a_return_whatever_the_leading_axes():
    bins = np.arange(512)
    pulse = np.exp(-0.5 * ((bins - 200) / 2.0) ** 2)
    rates = np.stack([0.002 + s * pulse / pulse.sum() for s in (1.5, 8.0)])  # a plain return, a saturated one
    counts = pileup.detection_probabilities(rates) * 50_000
    assert pileup.saturated_histograms(counts).tolist() == [False, True]
    grid = np.broadcast_to(counts, (3, 9, 2, 512))  # views, zones, ...
    assert pileup.saturated_histograms(grid).shape == (3, 9, 2) and pileup.saturated_histograms(grid)[..., 1].all()
    early = np.zeros(512)
    early[0] = 1e4  # a return in the first bin: nothing before it to judge by
    late_only = np.zeros(512)
    late_only[300] = 1e4  # no background at all
    assert not pileup.saturated_histograms(np.stack([early, late_only])).any()
    masked = np.ones((2, 512), bool)
    masked[:, :195] = False  # the bins before the return left out: nothing to judge by either
    assert not pileup.saturated_histograms(counts, masked).any()
    two = 2.5e-6 + (0.2 * np.roll(pulse, -50) + 0.4 * np.roll(pulse, 20)) / pulse.sum()  # an object, a table behind
    last = 0.002 + 8.0 * np.roll(pulse, 305) / pulse.sum()  # a saturated return in the last bins: nothing after
    assert not pileup.saturated_histograms(pileup.detection_probabilities(np.stack([two, last])) * 5_000).any()
    for bad in (np.full(512, np.nan), -counts, np.zeros((2, 0))):
        with pytest.raises(SimulationError):
            pileup.saturated_histograms(bad)
