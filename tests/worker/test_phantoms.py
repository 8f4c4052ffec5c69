"""Erosion of surface the histograms do not show: the photon ratio test and the per-node evidence
(worker/recon/fast/evidence.py), and the erosion itself (worker/recon/fast/parts/erosion.py)."""

from __future__ import annotations

import math

import pytest
import torch

from spadscan.worker.recon.fast.evidence import ReturnEvidence, return_ratios
from spadscan.worker.recon.fast.parts.erosion import deep_enough, erode_at


def peak(n_bins: int, at: int, photons: float) -> torch.Tensor:
    h = torch.zeros(n_bins, dtype=torch.float64)
    h[at - 1: at + 2] = torch.tensor([0.25, 0.5, 0.25], dtype=torch.float64) * photons
    return h


def test_a_predicted_return_with_no_measured_photons_reads_a_small_significant_ratio():
    bg = torch.tensor([2.0, 2.0, 100.0, 2.0], dtype=torch.float64)
    expected = bg[:, None] + torch.stack([peak(40, 20, 500.0), peak(40, 20, 500.0), peak(40, 20, 3.0),
                                          peak(40, 20, 500.0)])
    counts = expected.clone()
    counts[0] = bg[0]  # nothing came back where the model puts 500 photons
    valid = torch.ones_like(counts, dtype=torch.bool)
    valid[3, 18:23] = False  # bins the sensor does not record can neither confirm nor deny a return
    ratio, significant = return_ratios(expected, counts, bg, valid, window=2)
    assert float(ratio[0, 20]) < 0.01 and bool(significant[0, 20])
    assert float(ratio[1, 20]) == pytest.approx(1.0) and bool(significant[1, 20])
    assert not bool(significant[2, 20])  # 3 photons over a background of 100 per bin: noise could hide them
    assert float(ratio[3, 20]) == pytest.approx(1.0) and not bool(significant[3, 20])
    # Away from any return there is no signal either way: ratio 1, and nothing to test.
    assert float(ratio[1, 5]) == pytest.approx(1.0) and not bool(significant[1, 5])
    assert torch.isfinite(ratio).all()


def test_ratios_stay_finite_with_zero_photons_and_huge_counts():
    expected = torch.tensor([[0.0] * 8, [1e9] * 8], dtype=torch.float64)
    counts = torch.tensor([[0.0] * 8, [16777215.0] * 8], dtype=torch.float64)
    ratio, _ = return_ratios(expected, counts, torch.zeros(2, dtype=torch.float64),
                             torch.ones(2, 8, dtype=torch.bool), window=0)
    assert torch.isfinite(ratio).all() and float(ratio[0].min()) == 1.0
    with pytest.raises(ValueError, match="window"):
        return_ratios(expected, counts, torch.zeros(2), torch.ones(2, 8, dtype=torch.bool), window=-1)


def test_evidence_flags_nodes_with_enough_low_ratio_returns_and_then_starts_afresh():
    ev = ReturnEvidence((4, 5, 6), "cpu")
    origin, voxel = torch.tensor([0.0, 0.0, 0.0]), 0.01
    node = lambda x, y, z: torch.tensor([[x * voxel + 0.001, y * voxel - 0.002, z * voxel]])  # noqa: E731
    for _ in range(3):
        ev.add(node(1, 2, 3), torch.tensor([math.log(0.2)]), origin, voxel)  # three returns, all 0.2
    ev.add(node(4, 1, 0), torch.tensor([math.log(0.2)]), origin, voxel)  # one return only
    for r in (0.2, 1.5, 1.5):  # mean log ratio above log 0.6
        ev.add(node(2, 2, 2), torch.tensor([math.log(r)]), origin, voxel)
    ev.add(torch.tensor([[1.0, 1.0, 1.0], [-0.5, 0.0, 0.0]]), torch.tensor([-9.0, -9.0]), origin, voxel)  # off grid
    flagged = ev.take(min_hits=3, max_ratio=0.6)
    assert flagged.shape == (4, 5, 6)
    assert [tuple(i) for i in torch.nonzero(flagged).tolist()] == [(3, 2, 1)]  # (z, y, x)
    assert not ev.take(min_hits=1, max_ratio=0.6).any()  # taken: the next window starts empty


def test_erosion_moves_the_surface_one_voxel_inward_near_the_flagged_nodes_only():
    voxel = 0.01
    z = torch.arange(10, dtype=torch.float64)[:, None, None] * voxel
    sdf = (z - 0.055).expand(10, 8, 8).clone()  # solid below z = 5.5 voxels
    nodes = torch.zeros(10, 8, 8, dtype=torch.bool)
    nodes[5, 4, 4] = True
    before = sdf.clone()
    assert erode_at(sdf, nodes, voxel) == 1
    changed = (sdf - before).abs() > 0
    assert int(changed.sum()) == 27  # the node and its 26 neighbours
    assert torch.allclose((sdf - before)[changed], torch.tensor(voxel, dtype=torch.float64))
    # The surface there now lies one voxel lower, half-way between nodes 4 and 5 (it was between 5 and 6).
    assert float(sdf[4, 4, 4]) == pytest.approx(-0.5 * voxel) and float(sdf[5, 4, 4]) == pytest.approx(0.5 * voxel)
    assert float(sdf[5, 4, 6]) == pytest.approx(-0.5 * voxel)  # two nodes away: where it was
    assert erode_at(sdf, torch.zeros_like(nodes), voxel) == 0


def slab(thickness_voxels: float, voxel: float = 0.01, n: int = 16) -> torch.Tensor:
    """SDF grid (z, y, x) of a horizontal slab `thickness_voxels` thick, centred between nodes 7 and 8 in z."""
    z = torch.arange(n, dtype=torch.float64)[:, None, None] * voxel
    return ((z - 7.5 * voxel).abs() - 0.5 * thickness_voxels * voxel).expand(n, n, n).clone()


def test_the_depth_guard_keeps_a_thin_wall_and_passes_a_thick_solid():
    voxel = 0.01
    thin, thick = slab(2.0), slab(8.0)
    top = (8, 8, 8)  # a node next to the slab's upper face in both grids
    every = torch.ones(16, 16, 16, dtype=torch.bool)
    assert not bool(deep_enough(thin, every, 2 * voxel, voxel)[top])  # a 2-voxel wall is 1 voxel deep at most
    assert bool(deep_enough(thick, every, 2 * voxel, voxel)[top])
    assert bool(deep_enough(thin, every, 0.5 * voxel, voxel)[top])  # a shallower depth lets the thin wall through
    # Far from any solid (16 voxels of air above a thin slab) nothing is deep enough.
    assert not deep_enough(slab(2.0, n=40)[30:], torch.ones(10, 40, 40, dtype=torch.bool), 0.5 * voxel, voxel).any()


def test_the_depth_guard_answers_for_the_given_nodes_as_a_min_pool_over_the_grid_would():
    gen = torch.Generator().manual_seed(0)
    x = torch.arange(13, dtype=torch.float64)
    sdf = (x - 6.0) * 0.004 + torch.randn(9, 11, 13, generator=gen, dtype=torch.float64) * 0.002  # deep at low x
    nodes = torch.rand(9, 11, 13, generator=gen) < 0.3
    nodes[0, 0, 0] = nodes[-1, -1, -1] = True  # corners: their windows reach off the grid
    voxel, depth = 0.01, 0.015  # a window of 3 nodes either side
    lowest = -torch.nn.functional.max_pool3d(-sdf[None, None], 7, 1, 3)[0, 0]
    expected = nodes & (lowest <= -depth)
    assert 0 < int(expected.sum()) < int(nodes.sum())
    for chunk in (4096, 5):  # whole, and in chunks
        assert torch.equal(deep_enough(sdf, nodes, depth, voxel, chunk=chunk), expected)
    assert not deep_enough(sdf, torch.zeros_like(nodes), depth, voxel).any()
