"""The fast preset's gradient blur: a separable [1, 2, 1] / 4 filter with replicated edges."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from spadscan.worker.recon.fast.parts.blur import BlurConfig, GradientBlur, blur3


def reference(a: np.ndarray, passes: int) -> np.ndarray:
    """The same filter the slow, obvious way: pad by replication, weight the three shifted copies."""
    a = a.astype(np.float64)
    for _ in range(passes):
        for axis in (0, 1, 2):
            pad = [(0, 0)] * 3
            pad[axis] = (1, 1)
            p = np.pad(a, pad, mode="edge")
            n = a.shape[axis]
            a = 0.25 * np.take(p, range(0, n), axis) + 0.5 * np.take(p, range(1, n + 1), axis) + \
                0.25 * np.take(p, range(2, n + 2), axis)
    return a


@pytest.mark.parametrize("shape", [(7, 5, 6), (1, 4, 3), (2, 1, 9), (1, 1, 1)])
@pytest.mark.parametrize("passes", [0, 1, 3])
def test_matches_the_padded_three_tap_filter(shape, passes):
    a = np.random.default_rng(0).normal(size=shape)
    x = torch.tensor(a, dtype=torch.float64)[None, None]
    got = blur3(x, passes)[0, 0].numpy()
    np.testing.assert_allclose(got, reference(a, passes), atol=1e-12)
    assert torch.equal(x[0, 0], torch.tensor(a))  # the input is left as it was


def test_spreads_a_spike_to_its_neighbours_and_keeps_constants():
    x = torch.zeros(1, 1, 5, 5, 5)
    x[0, 0, 2, 2, 2] = 1.0
    y = blur3(x, 1)[0, 0]
    assert y[2, 2, 2] == pytest.approx(0.125)
    assert y[1, 2, 2] == pytest.approx(0.0625) and y[1, 1, 1] == pytest.approx(1 / 64)
    assert float(y.sum()) == pytest.approx(1.0)  # away from the edges the filter moves mass, never makes it
    c = torch.full((1, 1, 4, 3, 5), 2.5)
    assert torch.allclose(blur3(c, 2), c)


def test_rejects_bad_input():
    with pytest.raises(ValueError):
        blur3(torch.zeros(1, 1, 3, 3, 3), -1)
    with pytest.raises(ValueError):
        blur3(torch.zeros(3, 3, 3), 1)


def spread_m2(grad: torch.Tensor, voxel_m: float) -> float:
    """Variance (square metres) along the first axis of a grid's mass around its centre node."""
    w = grad[0, 0].sum(dim=(1, 2)).double()
    z = (torch.arange(len(w), dtype=torch.float64) - len(w) // 2) * voxel_m
    return float((w * z * z).sum() / w.sum())


def test_the_physical_blur_reaches_as_far_in_metres_on_the_fine_level_as_on_the_coarse_one():
    def impulse(n):
        g = torch.zeros(1, 1, n, n, n)
        g[0, 0, n // 2, n // 2, n // 2] = 1.0
        return g

    coarse_voxel = 0.004
    blur = GradientBlur(BlurConfig(physical=True), SimpleNamespace())
    coarse = spread_m2(blur.after_gradient(SimpleNamespace(level=0), impulse(17)), coarse_voxel)
    fine = spread_m2(blur.after_gradient(SimpleNamespace(level=1), impulse(33)), coarse_voxel / 2)
    assert coarse == pytest.approx(0.5 * coarse_voxel ** 2)  # one pass: half a voxel squared
    assert fine == pytest.approx(coarse)
    fixed = GradientBlur(BlurConfig(physical=False), SimpleNamespace())
    assert spread_m2(fixed.after_gradient(SimpleNamespace(level=1), impulse(33)), coarse_voxel / 2) == \
        pytest.approx(coarse / 4)
