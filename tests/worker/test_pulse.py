"""The pulse derived from a measured capture's reference histogram (worker/pulse.py)."""

from __future__ import annotations

import numpy as np
import pytest

from spadscan.worker import pulse


def reference(n: int = 64, peak: float = 20.3, floor: float = 50.0) -> np.ndarray:
    """A reference histogram: a skewed pulse (fast rise, slow tail) on a constant floor, counts per bin."""
    i = np.arange(n, dtype=float)
    rise = np.exp(-0.5 * ((i - peak) / 0.8) ** 2)
    tail = np.exp(-(i - peak) / 3.9)
    return floor + 2e4 * np.where(i < peak, rise, tail)


def test_rising_edge_is_steepened_relative_to_the_peak_and_the_tail_keeps_its_shape(monkeypatch):
    ref = reference()
    steep = pulse.reference_kernel(ref)
    monkeypatch.setattr(pulse, "REF_RISE_POWER", 1.0)
    plain = pulse.reference_kernel(ref)
    assert steep.shape == plain.shape and np.isclose(steep.sum(), 1.0) and np.all(steep >= 0)
    top = int(np.argmax(plain))
    assert int(np.argmax(steep)) == top
    # Before the peak: (bin / peak) squared; from the peak on: the same shape, rescaled by the renormalisation.
    np.testing.assert_allclose(steep[:top] / steep[top], (plain[:top] / plain[top]) ** 2, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(steep[top:] / steep[top], plain[top:] / plain[top], rtol=1e-12)
    assert steep[top - 1] < plain[top - 1] and steep[top] > plain[top]


@pytest.mark.parametrize("oversample", [1, 4])
def test_reference_kernel_stays_finite_and_refuses_a_reference_without_a_peak(oversample):
    k = pulse.reference_kernel(reference(), oversample)
    assert k.shape == ((pulse.KERNEL_BEFORE + pulse.KERNEL_AFTER + 1) * oversample,)
    assert np.all(np.isfinite(k)) and np.isclose(k.sum(), 1.0)
    assert pulse.reference_kernel(np.full(64, 50.0), oversample) is None  # flat: no pulse
    assert pulse.reference_kernel(np.zeros(64), oversample) is None  # zero photons
    assert pulse.reference_kernel(np.r_[np.full(63, 50.0), np.nan], oversample) is None
