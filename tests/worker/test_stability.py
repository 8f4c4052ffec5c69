"""Numerical stability of the renderer and the sensor model on stiff and extreme inputs (issue: numerical stability).

Each case must stay finite (values and gradients) or fail with a clear one-line error.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker.recon.errors import ReconstructionError
from spadscan.worker.recon.forward import ModelTerms, TransientForward
from spadscan.worker.recon.paper.loss import hist_l2, hist_scale
from spadscan.worker.recon.paper.mesh import marching_cubes_mesh
from spadscan.worker.recon.paper.config import MLPFieldConfig
from spadscan.worker.recon.paper.field import MLPField
from spadscan.worker.recon.paper.rays import ZoneGrid
from spadscan.worker.recon.paper.render import SphereField, render_rays
from worker_helpers import sensor_forward

F32, F64 = torch.float32, torch.float64


pytestmark = pytest.mark.usefixtures("one_thread")


def rays_at_sphere(n=16, dtype=F64, spread=0.26):
    """Rays from (0, 0, -0.4) toward a 0.1 m sphere at the origin; the outermost pass at grazing incidence."""
    ang = torch.linspace(0, spread, n, dtype=dtype)
    d = torch.stack([torch.sin(ang), torch.zeros_like(ang), torch.cos(ang)], -1)
    return torch.tensor([0.0, 0.0, -0.4], dtype=dtype).expand(n, 3), d


@pytest.mark.parametrize("dtype", [F32, F64])
@pytest.mark.parametrize("s", [1.0, 1e4, 1e6, 1e9])
def test_extreme_sharpness_stays_finite_with_finite_gradients(dtype, s):
    o, d = rays_at_sphere(dtype=dtype)
    field = SphereField([0.0, 0.0, 0.0], 0.1, dtype=dtype)
    log_s = torch.tensor(math.log(s), dtype=dtype, requires_grad=True)
    t = torch.linspace(0.2, 0.6, 128, dtype=dtype).expand(len(o), -1)
    out = render_rays(field, o, d, t, torch.exp(log_s), 1.0)
    out.radiance.sum().backward()
    assert torch.isfinite(out.radiance).all() and torch.isfinite(out.transmittance).all()
    for g in (log_s.grad, field.radius.grad, field.center.grad):
        assert torch.isfinite(g).all()


def test_grazing_rays_and_zero_gradients_stay_finite():
    o, d = rays_at_sphere(64, spread=math.asin(0.1 / 0.4) * 1.01)  # the last ray misses by ~1 mm, the ones before graze
    field = SphereField([0.0, 0.0, 0.0], 0.1)
    t = torch.linspace(0.2, 0.6, 256, dtype=F64).expand(len(o), -1)
    out = render_rays(field, o, d, t, 1e5, 1.0)
    out.radiance.sum().backward()
    assert torch.isfinite(out.radiance).all() and torch.isfinite(field.radius.grad)
    assert float(out.radiance[-1].detach().sum()) == pytest.approx(0.0, abs=1e-9)
    # A point at the centre of an analytic sphere has no direction: its normal falls back, never NaN.
    class Flat(SphereField):
        def sdf_and_grad(self, x, create_graph=True):
            return super().sdf(x), torch.zeros_like(x)

    flat = render_rays(Flat([0.0, 0.0, 0.0], 0.1), o, d, t, 1e5, 1.0)
    assert torch.isfinite(flat.radiance).all()


def test_samples_a_millimetre_from_the_sensor_and_on_it():
    field = SphereField([0.0, 0.0, 0.0051], 0.005)  # surface 0.1 mm in front of the sensor at the origin
    o = torch.zeros(1, 3, dtype=F64)
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    for t0 in (1e-3, 0.0):
        t = torch.linspace(t0, 0.02, 64, dtype=F64)[None]
        out = render_rays(field, o, d, t, 1e5, 1.0)
        out.radiance.sum().backward()
        assert torch.isfinite(out.radiance).all() and float(out.radiance.detach().sum()) > 0
        assert torch.isfinite(field.radius.grad)
    fw = sensor_forward(sensor_preset("tmf8820"))
    tr = fw.bin(out.ranges.reshape(-1), out.radiance.detach().reshape(-1), torch.zeros(63, dtype=torch.long), 9)
    lam = fw.rates(tr.reshape(1, 9, -1), 1e-5)
    assert torch.isfinite(lam).all() and torch.isfinite(fw.detections(lam)).all()


@pytest.mark.parametrize("flux", [1e-12, 1.0, 1e3, 1e8, 1e14, 1e16])
def test_flux_up_to_and_past_saturation(flux):
    sensor = sensor_preset("tmf8820")
    fw = sensor_forward(sensor)
    lam = torch.full((1, 9, sensor.n_bins), 1e-4, dtype=F64)
    lam[..., 30:34] = flux
    lam.requires_grad_(True)
    p = fw.detections(lam)
    assert torch.isfinite(p).all() and float(p.detach().sum(-1).max()) <= 1.0 + 1e-12
    counts = (p.detach() * sensor.cycles).round()
    cycles = torch.tensor([float(sensor.cycles)], dtype=F64)
    nll = fw.nll(lam, counts, cycles)
    l2 = hist_l2(fw, lam, counts, cycles, torch.ones_like(counts, dtype=torch.bool), 1e-3)
    (nll + l2).backward()
    assert torch.isfinite(nll) and torch.isfinite(l2) and torch.isfinite(lam.grad).all()


def test_zero_photon_histograms():
    sensor = sensor_preset("lcspc-sim")
    fw = sensor_forward(sensor, pileup=True)
    counts = torch.zeros(2, 1, sensor.n_bins, dtype=F64)
    cycles = torch.full((2,), 5000.0, dtype=F64)
    valid = torch.ones_like(counts, dtype=torch.bool)
    bg = torch.full((2, 1), 1e-12, dtype=F64)
    scale = hist_scale(counts, cycles, valid, bg)
    assert scale > 0
    lam = fw.rates(torch.zeros(2, 1, sensor.n_bins, dtype=F64, requires_grad=True), bg)
    for fn in (lambda: fw.nll(lam, counts, cycles), lambda: hist_l2(fw, lam, counts, cycles, valid, scale)):
        v = fn()
        assert torch.isfinite(v)
    fw_no = sensor_forward(sensor, pileup=False)
    assert torch.isfinite(fw_no.nll(lam, counts, cycles))


def test_24_bit_saturated_counts():
    sensor = sensor_preset("tmf8820")
    fw = sensor_forward(sensor)
    counts = torch.full((1, 9, sensor.n_bins), 150.0, dtype=F64)
    counts[..., 20:30] = float(2 ** 24 - 1)  # far more than the cycles can explain
    cycles = torch.tensor([4e6], dtype=F64)
    lam = torch.full_like(counts, 1e-4).requires_grad_(True)
    v = fw.nll(lam, counts, cycles)
    v.backward()
    assert torch.isfinite(v) and torch.isfinite(lam.grad).all()


@pytest.mark.parametrize("factor", [0.1, 10.0])
def test_bins_ten_times_finer_or_coarser_conserve_the_signal(factor):
    base = sensor_preset("tmf8820")
    o = torch.tensor([[0.0, 0.0, -0.3]], dtype=F64)
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    field = SphereField([0.0, 0.0, 0.0], 0.1)
    t = torch.linspace(0.05, 0.5, 400, dtype=F64)[None]
    out = render_rays(field, o, d, t, 1e5, 1.0)
    totals, peaks = [], []
    # The same pulse in metres on bins 10x finer or coarser (its width in bins scales inversely).
    pulse = base.pulse
    other = base.with_(bin_width_m=base.bin_width_m * factor, n_bins=max(8, int(round(base.n_bins / factor))),
                       zero_bin=base.zero_bin / factor,
                       pulse=type(pulse)(kind="exgauss", sigma_bins=pulse.sigma_bins / factor,
                                         tau_bins=pulse.tau_bins / factor))
    for sensor in (base, other):
        fw = sensor_forward(sensor)
        tr = fw.bin(out.ranges.reshape(-1), out.radiance.detach().reshape(-1), torch.zeros(399, dtype=torch.long), 9)
        lam = fw.rates(tr.reshape(1, 9, -1), 0.0) - 0.0
        assert torch.isfinite(lam).all()
        sig = lam[0, 4]
        totals.append(float(sig.sum()))
        peaks.append(float(sensor.range_of_bin((sig * (torch.arange(len(sig)) + 0.5)).sum() / sig.sum())))
    assert totals[1] == pytest.approx(totals[0], rel=0.02)
    assert abs(peaks[1] - peaks[0]) < 2 * base.bin_width_m * max(1.0, factor)


def test_float32_and_float64_renderers_agree():
    cfg = MLPFieldConfig(width=48, layers=4, skip_layers=(2,), frequencies=4)
    torch.manual_seed(0)
    f64 = MLPField(cfg, torch.zeros(3, dtype=F64), 0.2).to(F64)
    f32 = MLPField(cfg, torch.zeros(3), 0.2)
    f32.load_state_dict({k: v.float() for k, v in f64.state_dict().items()})
    o64, d64 = rays_at_sphere(32, spread=0.4)
    t64 = torch.linspace(0.15, 0.65, 96, dtype=F64).expand(32, -1)
    for s in (50.0, 2e3):
        r64 = render_rays(f64, o64, d64, t64, s, 0.8).radiance.detach()
        r32 = render_rays(f32, o64.float(), d64.float(), t64.float(), s, 0.8).radiance.detach()
        assert float(r64.sum()) > 0
        assert float((r32.double() - r64).abs().sum() / r64.sum()) < 1e-4


def test_pipeline_gradient_of_an_mlp_field_by_finite_differences():
    """d(loss)/d(last layer) through field -> renderer -> binning -> pulse -> pile-up -> likelihood, in float64."""
    cfg = MLPFieldConfig(width=8, layers=2, skip_layers=(), frequencies=2, weight_norm=False)
    torch.manual_seed(1)
    field = MLPField(cfg, torch.zeros(3, dtype=F64), 0.2).to(F64)
    sensor = sensor_preset("tmf8820").with_(n_bins=48)
    fw = sensor_forward(sensor)
    o, d = rays_at_sphere(6, spread=0.3)
    t = torch.linspace(0.2, 0.6, 24, dtype=F64).expand(6, -1)
    counts = torch.tensor(np.random.default_rng(0).integers(0, 30, (1, 9, 48)), dtype=F64)
    cycles = torch.tensor([1e4], dtype=F64)
    last = field.linears[-1]
    hist = (torch.arange(6) % 9).repeat_interleave(23)

    def loss(weight, bias):
        last.weight, last.bias = weight, bias
        out = render_rays(field, o, d, t, 40.0, 0.7)
        tr = fw.bin(out.ranges.reshape(-1), (0.01 * out.radiance).reshape(-1), hist, 9)
        return fw.nll(fw.rates(tr.reshape(1, 9, -1), 1e-3), counts, cycles)

    w = last.weight.detach().clone().requires_grad_(True)
    b = last.bias.detach().clone().requires_grad_(True)
    del last.weight, last.bias  # plain tensors from here on, so that gradcheck can perturb them
    assert torch.autograd.gradcheck(loss, (w, b), eps=1e-6, atol=1e-5, rtol=1e-3)


def test_clear_errors_where_no_answer_exists():
    sensor = sensor_preset("tmf8820")
    with pytest.raises(ReconstructionError, match="rays per zone"):
        ZoneGrid(sensor, 0)
    with pytest.raises(ReconstructionError, match="pulse"):
        TransientForward(sensor, ModelTerms(True, True, False, False, False), torch.tensor([float("nan")]), 0)
    box = torch.tensor([[-0.1, -0.1, -0.1], [0.1, 0.1, 0.1]], dtype=F64)
    with pytest.raises(ReconstructionError, match="no surface"):
        marching_cubes_mesh(lambda x: x.norm(dim=-1) + 1.0, None, box, 16)
    with pytest.raises(ReconstructionError, match="not finite"):
        marching_cubes_mesh(lambda x: x[:, 0] * float("nan"), None, box, 16)
