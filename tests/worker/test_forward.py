"""The torch sensor model against the protocol simulator, and its binning, pile-up, likelihoods and term choice."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from spadscan.protocol import pileup
from spadscan.protocol.schedules import look_at
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, Simulator
from spadscan.worker.recon.errors import ReconstructionError
from spadscan.worker.recon.forward import choose_terms
from spadscan.worker.recon.paper.pipeline import render_transients, world_rays
from spadscan.worker.recon.paper.rays import zone_rays
from spadscan.worker.recon.paper.render import SphereField
from spadscan.worker.recon.paper.sampler import sphere_interval, stratified
from worker_helpers import sensor_forward

F64 = torch.float64


pytestmark = pytest.mark.usefixtures("one_thread")


def render_sphere_rates(sensor, poses, center, radius, rays_per_zone, samples):
    """Rates (V, Z, B) of an analytic sphere through the renderer and the forward model (float64, sharp)."""
    fw = sensor_forward(sensor, oversample=8)
    field = SphereField(center, radius)
    dirs, w = zone_rays(sensor, rays_per_zone, jitter=True, generator=torch.Generator().manual_seed(1), dtype=F64)
    org, d = world_rays(torch.tensor(poses), dirs)
    v, z, r, _ = d.shape
    near, far, hit = sphere_interval(org.reshape(-1, 3), d.reshape(-1, 3), torch.tensor(center), radius * 1.15, 0.01)
    t = stratified(near, far, samples, jitter=False).reshape(v * z, r, samples)
    weight = w[None].expand(v, z, r).reshape(v * z, r) * hit.reshape(v * z, r)
    with torch.no_grad():
        tr, _ = render_transients(field, fw, org.reshape(v * z, r, 3), d.reshape(v * z, r, 3), weight, t,
                                  1e6, 1.0, create_graph=False)
        return fw.rates(tr.reshape(v, z, -1), sensor.background).numpy()


@pytest.mark.parametrize("preset, rays, samples", [("tmf8820", 400, 160), ("lcspc-sim", 3000, 160)])
def test_rendered_sphere_matches_simulated_sphere_mesh(preset, rays, samples):
    import trimesh

    sensor = sensor_preset(preset)
    center, radius = np.array([0.0, 0.0, 0.06]), 0.06
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    mesh.apply_translation(center)
    poses = np.stack([look_at((0.3, 0.0, 0.1), center), look_at((0.02, -0.18, 0.3), center + [0.01, 0, 0])])
    sim = Simulator(mesh, sensor, SimSettings(rays_per_zone=4096), seed=0)
    want = sim.expected_rates(poses) - sensor.background
    got = render_sphere_rates(sensor, poses, center, radius, rays, samples) - sensor.background
    peak = want.max(axis=-1, keepdims=True)
    assert np.all(peak > 1e-6), "every histogram must see the sphere"
    err = np.abs(got - want) / peak
    assert err.max() < 0.04, f"worst bin off by {err.max():.1%} of its histogram's peak"
    np.testing.assert_allclose(got.sum(-1), want.sum(-1), rtol=0.03)
    np.testing.assert_array_equal(got.argmax(-1), want.argmax(-1))


def test_bin_conserves_mass_and_mean_arrival():
    sensor = sensor_preset("lcspc-sim")
    fw = sensor_forward(sensor, oversample=4)
    ranges = torch.tensor([0.2, 0.2001, 0.35, 0.5], dtype=F64)
    rad = torch.tensor([1.0, 2.0, 0.5, 0.25], dtype=F64)
    hist = torch.tensor([0, 0, 1, 1])
    out = fw.bin(ranges, rad, hist, 2)
    assert out.shape == (2, fw.n_fine)
    torch.testing.assert_close(out.sum(-1), torch.tensor([3.0, 0.75], dtype=F64))
    # The mean arrival (in fine-cell centres) is exact under linear splitting.
    centres = torch.arange(fw.n_fine, dtype=F64) + 0.5
    arrival = lambda r: (sensor.zero_bin + fw.pad_lo + r / sensor.bin_width_m) * fw.oversample  # noqa: E731
    mean0 = (out[0] * centres).sum() / out[0].sum()
    assert float(mean0) == pytest.approx((arrival(0.2) + 2 * arrival(0.2001)) / 3, abs=1e-9)


def test_bin_drops_returns_off_the_axis_and_nonfinite_ranges():
    sensor = sensor_preset("tmf8820")
    fw = sensor_forward(sensor, oversample=2)
    ranges = torch.tensor([-5.0, 50.0, float("nan"), float("inf"), 0.3], dtype=F64)
    out = fw.bin(ranges, torch.ones(5, dtype=F64), torch.zeros(5, dtype=torch.long), 1)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out.sum(), torch.tensor(1.0, dtype=F64))


def test_per_bin_transient_equals_evenly_spread_fine_transient():
    sensor = sensor_preset("tmf8820")
    fw = sensor_forward(sensor, oversample=4)
    per_bin = torch.zeros(1, 9, sensor.n_bins, dtype=F64)
    per_bin[0, :, 40] = 1.0
    # The same returns, spread evenly over bin 40 on the fine axis.
    u = torch.arange(4, dtype=F64) / 4 + 1 / 8
    ranges = ((40 + u) - sensor.zero_bin) * sensor.bin_width_m
    fine = torch.stack([fw.bin(ranges, torch.full((4,), 0.25, dtype=F64), torch.zeros(4, dtype=torch.long), 1)[0]
                        for _ in range(9)])[None]
    torch.testing.assert_close(fw.rates(per_bin, 1e-6), fw.rates(fine, 1e-6))


def test_rates_apply_gains_crosstalk_and_background():
    sensor = sensor_preset("tmf8820")
    fw = sensor_forward(sensor, oversample=1)
    tr = torch.zeros(1, 9, sensor.n_bins, dtype=F64)
    tr[0, 4, 50] = 1.0  # only the centre zone sees anything
    lam = fw.rates(tr, torch.full((1, 9), 1e-5, dtype=F64))
    sig = lam - 1e-5
    centre = sig[0, 4].sum()
    torch.testing.assert_close(centre, torch.tensor(sensor.signal_scale * math.pi * (1 + sensor.crosstalk),
                                                    dtype=F64))
    for z in range(9):
        if z != 4:  # every other zone gets crosstalk x the centre zone's signal
            torch.testing.assert_close(sig[0, z].sum(), torch.tensor(sensor.signal_scale * math.pi *
                                                                     sensor.crosstalk, dtype=F64))


def test_rates_refuse_wrong_shapes():
    fw = sensor_forward(sensor_preset("tmf8820"), oversample=1)
    with pytest.raises(ReconstructionError, match="bins"):
        fw.rates(torch.zeros(1, 9, 77, dtype=F64), 1e-6)
    with pytest.raises(ReconstructionError, match="zones"):
        fw.rates(torch.zeros(1, 4, 128, dtype=F64), 1e-6)


def test_detections_match_the_protocol_pileup():
    sensor = sensor_preset("lcspc-sim")
    fw = sensor_forward(sensor, oversample=8)
    rng = np.random.default_rng(0)
    lam = rng.gamma(0.5, 0.01, size=(2, 1, sensor.n_bins))
    lam[0, 0, 300] = 3.0  # a saturating peak
    got = fw.detections(torch.tensor(lam)).numpy()
    np.testing.assert_allclose(got, pileup.detection_probabilities(lam), rtol=1e-10, atol=1e-15)
    assert got.sum(-1).max() <= 1.0


def test_nll_is_smallest_at_the_true_rates_and_finite_at_extremes():
    sensor = sensor_preset("lcspc-sim")
    for pile in (True, False):
        fw = sensor_forward(sensor, pileup=pile, oversample=1)
        lam = torch.full((1, 1, sensor.n_bins), 2e-4, dtype=F64)
        lam[0, 0, 400:410] = 0.05
        rng = np.random.default_rng(1)
        p = fw.detections(lam).numpy()[0, 0]
        counts = rng.multinomial(5000, np.append(p, 1 - p.sum()))[:-1] if pile else rng.poisson(p * 5000)
        counts = torch.tensor(counts[None, None], dtype=F64)
        cyc = torch.tensor([5000.0], dtype=F64)
        best = fw.nll(lam, counts, cyc)
        for scale in (0.7, 1.4):
            assert fw.nll(lam * scale, counts, cyc) > best
        for extreme in (torch.zeros_like(lam), torch.full_like(lam, 1e30)):
            x = extreme.clone().requires_grad_(True)
            v = fw.nll(x, counts, cyc)
            v.backward()
            assert torch.isfinite(v) and torch.isfinite(x.grad).all()


def test_choose_terms_follow_the_capture():
    from types import SimpleNamespace

    def scene(preset, counts_per_cycle, table=None, real=False):
        s = sensor_preset(preset)
        counts = torch.full((2, s.n_zones, s.n_bins), counts_per_cycle * 1000.0 / s.n_bins)
        return SimpleNamespace(sensor=s, counts=counts, valid=torch.ones_like(counts, dtype=torch.bool),
                               cycles=torch.full((2,), 1000.0), table=table, real=real, pulse_source="sensor model")

    low = choose_terms(scene("lcspc-sim", 0.001))
    assert not low.pileup and not low.crosstalk and not low.table and not low.tv
    assert choose_terms(scene("lcspc-sim", 0.3)).pileup
    tmf = choose_terms(scene("tmf8820", 0.5, table=object(), real=True))
    assert tmf.pileup and tmf.crosstalk and tmf.table and tmf.tv


def test_gradients_of_binning_rates_and_likelihood_by_finite_differences():
    sensor = sensor_preset("tmf8820").with_(n_bins=24, zero_bin=2.0, jitter_bins=0.0)
    fw = sensor_forward(sensor, oversample=2)
    counts = torch.tensor(np.random.default_rng(2).integers(0, 50, (1, 9, 24)), dtype=F64)
    cyc = torch.tensor([2000.0], dtype=F64)
    hist = torch.tensor([0, 3, 8])

    def loss(ranges, radiance):
        tr = fw.bin(ranges, radiance, hist, 9).reshape(1, 9, -1)
        return fw.nll(fw.rates(tr, 1e-3), counts, cyc)

    ranges = torch.tensor([0.05, 0.111, 0.173], dtype=F64, requires_grad=True)
    radiance = torch.tensor([0.3, 0.2, 0.5], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(loss, (ranges, radiance), eps=1e-7, atol=1e-5, rtol=1e-4)


def _drawn_histograms(fw, sensor, lam, cycles, seed=0):
    """Counts (V, Z, B) drawn from the rates' own detection probabilities over `cycles` (V,) cycles."""
    rng = np.random.default_rng(seed)
    p = fw.detections(lam).numpy()
    return torch.tensor(rng.poisson(p * cycles.numpy()[:, None, None]), dtype=lam.dtype)


@pytest.mark.parametrize("pile", [True, False])
@pytest.mark.parametrize("jitter", [0.0, 1.0])
def test_a_histogram_without_valid_bins_leaves_the_nll_and_its_gradient_alone(pile, jitter):
    """A dropped frame (every bin invalid) adds nothing: the loss and its gradient are those of the views without
    it. With pile-up its 'no photon in N cycles' term said the zone saw nothing, and pulled the fit."""
    sensor = sensor_preset("lcspc-sim").with_(jitter_bins=jitter)
    fw = sensor_forward(sensor, pileup=pile, oversample=1)
    lam = torch.full((3, 1, sensor.n_bins), 2e-4, dtype=F64)
    lam[:, 0, 400:410] = 0.05
    cycles = torch.full((3,), 5000.0, dtype=F64)
    counts = _drawn_histograms(fw, sensor, lam, cycles)
    counts[1] = 0.0
    valid = torch.ones_like(counts, dtype=torch.bool)
    valid[1] = False
    kept = torch.tensor([0, 2])
    full = lam.clone().requires_grad_(True)
    loss = fw.nll(full, counts, cycles, valid)
    loss.backward()
    alone = lam[kept].clone().requires_grad_(True)
    loss_kept = fw.nll(alone, counts[kept], cycles[kept], valid[kept])
    loss_kept.backward()
    assert float(loss.detach()) == pytest.approx(float(loss_kept.detach()), rel=1e-12)
    assert float(full.grad[1].abs().max()) == 0.0
    torch.testing.assert_close(full.grad[kept], alone.grad, rtol=1e-12, atol=0.0)


def test_jittered_nll_stays_finite_with_denormals_flushed():
    """Behind a saturating return the jittered detection probabilities underflow; under flush_denormals (the fast
    preset on the CPU) a denormal floor read 0, and log(0) made the loss nan."""
    from spadscan.worker.recon.numerics import flush_denormals

    sensor = sensor_preset("lcspc-sim").with_(jitter_bins=1.0)
    fw = sensor_forward(sensor, dtype=torch.float32, oversample=1)
    lam = torch.full((1, 1, sensor.n_bins), 2.5e-4)
    lam[..., 10] = 100.0
    counts = torch.zeros(1, 1, sensor.n_bins)
    counts[..., 10] = 5000.0
    cycles = torch.tensor([5000.0])
    plain = float(fw.nll(lam, counts, cycles))
    x = lam.clone().requires_grad_(True)
    with flush_denormals(torch.device("cpu")):
        assert float(torch.tensor([1e-39]).clamp_min(0.0)) == 0.0  # the mode is on: denormals read 0
        loss = fw.nll(x, counts, cycles)
        loss.backward()
    assert math.isfinite(float(loss.detach())) and float(loss.detach()) == pytest.approx(plain, rel=1e-6)
    assert torch.isfinite(x.grad).all()


@pytest.mark.parametrize("cycles, rel", [(4e6, 1e-3), (4e8, 1e-5), (4e9, 1e-5), (1e10, 1e-5)])
def test_float32_nll_reports_the_float64_deviance_for_views_of_many_cycles(cycles, rel):
    """A view sums its frames' cycles (up to 1e10 and more): the float32 deviance, a difference of terms of size
    c log(c/N), read 0.40 instead of 0.42 per bin at 4e8 cycles and -0.72 instead of 0.51 at 4e9. Past
    EXACT_ABOVE_CYCLES the value is the float64 one; below (a TMF8820 frame's 4e6), float32's own, within 1e-3; the
    gradient stays close to it."""
    sensor = sensor_preset("tmf8820")
    fw32, fw64 = sensor_forward(sensor, dtype=torch.float32), sensor_forward(sensor)
    lam = torch.full((1, 9, sensor.n_bins), 3e-5, dtype=torch.float32)
    lam[..., 40:46] += torch.tensor([0.001, 0.01, 0.03, 0.02, 0.01, 0.003])
    n = torch.tensor([cycles], dtype=F64)
    counts = _drawn_histograms(fw64, sensor, lam.double(), n).float()  # values float32 holds exactly, for both
    x32, x64 = lam.clone().requires_grad_(True), lam.double().requires_grad_(True)
    v32, v64 = fw32.nll(x32, counts, n.float()), fw64.nll(x64, counts.double(), n)
    (v32 + v64).backward()
    assert 0.3 < float(v64.detach()) / sensor.n_bins < 0.7  # about 0.5 per bin: drawn from the rates themselves
    assert float(v32.detach()) == pytest.approx(float(v64.detach()), rel=rel)
    assert float((x32.grad.double() - x64.grad).abs().max()) < 1e-2 * float(x64.grad.abs().max())


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("flux", [1e14, 1e16])
def test_expected_counts_never_exceed_the_cycles_at_the_largest_flux(dtype, flux):
    """signal_scale up to 1e9 on a surface at the 1 mm range floor gives up to ~2e14 photons per bin per cycle. The
    rates before such a bin must not cancel against it: `cumsum - lam` lost them, and the expected counts came to
    1.003 x the cycles at 1e14."""
    sensor = sensor_preset("tmf8820")
    fw = sensor_forward(sensor, dtype=dtype)
    lam = torch.full((1, 9, sensor.n_bins), 1e-4, dtype=dtype)
    lam[..., 30:34] = flux
    cycles = torch.tensor([float(sensor.cycles)], dtype=dtype)
    expected = fw.expected_counts(lam, cycles)
    tol = 1e-12 if dtype == F64 else 1e-6
    assert float(expected.sum(-1).max()) <= sensor.cycles * (1 + tol)
    np.testing.assert_allclose(fw.detections(lam).double().numpy(), pileup.detection_probabilities(lam.double().numpy()),
                               rtol=10 * tol, atol=1e-300)
