"""The NeuS-style renderer, the zone rays and the samplers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import MIN_RANGE_M as SIMULATOR_MIN_RANGE_M
from spadscan.worker.recon.paper.rays import ZoneGrid, mixture_weights, zone_rays
from spadscan.worker.recon.paper.render import (MIN_RANGE_M, SDFField, SphereField, Table, opacity, render_rays,
                                               round_trip_transmittance)
from spadscan.worker.recon.paper.sampler import importance, sphere_interval, stratified

F64 = torch.float64


def analytic_sphere_return(o, d, center, radius):
    """cos(incidence) / t^2 at the first hit of rays (R, 3) on a sphere, 0 for misses."""
    oc = o - center
    b = (oc * d).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - radius ** 2)
    t = -b - torch.sqrt(disc.clamp_min(0))
    n = (oc + t[:, None] * d) / radius
    return torch.where(disc > 0, -(n * d).sum(-1) / t ** 2, torch.zeros_like(t))


def fan(n=7, max_angle=0.24, dtype=F64):
    """Rays from (0, 0, -0.4) fanning toward a unit sphere of radius 0.1 at the origin, the last ones grazing."""
    ang = torch.linspace(0, max_angle, n, dtype=dtype)
    d = torch.stack([torch.sin(ang), torch.zeros_like(ang), torch.cos(ang)], -1)
    o = torch.tensor([0.0, 0.0, -0.4], dtype=dtype).expand(n, 3)
    return o, d


def test_sharp_rendering_of_a_sphere_matches_the_analytic_return():
    o, d = fan()
    field = SphereField([0.0, 0.0, 0.0], 0.1)
    t = torch.linspace(0.2, 0.6, 512, dtype=F64).expand(len(o), -1)
    out = render_rays(field, o, d, t, 1e7, 1.0)  # s x spacing >> 1: the opacity is a step
    got = out.radiance.sum(-1) * math.pi  # the renderer returns albedo / pi x cos / r^2
    want = analytic_sphere_return(o, d, field.center, 0.1)
    torch.testing.assert_close(got.detach(), want.detach(), rtol=0.01, atol=1e-9)
    # Returns sit at the hit range, and nothing passes an opaque surface.
    hit = want > 0
    peak = out.ranges.gather(1, out.radiance.argmax(-1, keepdim=True))[:, 0]
    b = (o * d).sum(-1)
    t_hit = -b - torch.sqrt(b * b - ((o * o).sum(-1) - 0.01))
    torch.testing.assert_close(peak[hit], t_hit[hit], rtol=0, atol=0.4 / 511)
    assert float(out.transmittance[hit].detach().max()) < 1e-6


def test_soft_opacity_loses_mass_to_the_round_trip_as_published():
    """With s comparable to the sample spacing the round trip returns less than an opaque surface would: a known
    property of prod (1 - alpha)^2 weights (the learned albedo absorbs it); sharper is closer to exact."""
    o, d = fan(1)
    field = SphereField([0.0, 0.0, 0.0], 0.1)
    t = torch.linspace(0.2, 0.6, 512, dtype=F64)[None]
    ratios = [float(render_rays(field, o, d, t, s, 1.0).radiance.detach().sum() * math.pi * 0.09)
              for s in (300.0, 1e4, 1e6)]  # returned / exact (cos / r^2 = 1 / 0.3^2 on the axis)
    assert ratios[0] < ratios[1] < ratios[2] <= 1.01
    assert ratios[2] > 0.99


def test_opacity_and_transmittance_bounds():
    f = torch.tensor([[1.0, 0.5, 0.0, -0.5, -1.0, -0.5, 0.5]], dtype=F64)
    for s in (1.0, 50.0, 1e4, 1e8):
        a = opacity(f, s)
        assert torch.all((a >= 0) & (a <= 1))
        assert torch.all(a[0, 4:] == 0)  # leaving the surface adds no opacity
        t = round_trip_transmittance(a)
        assert t[0, 0] == 1 and torch.all(t[0, 1:] <= t[0, :-1])


def test_table_plane_is_rendered_exactly_behind_the_object():
    table = Table(torch.tensor([0.0, 0.0, 1.0], dtype=F64), torch.tensor(-0.05, dtype=F64),
                  torch.tensor(0.5, dtype=F64))
    o = torch.tensor([[0.3, 0.0, 0.3]], dtype=F64)
    d = torch.tensor([[-0.6, 0.0, -0.8]], dtype=F64)
    field = SphereField([5.0, 5.0, 5.0], 0.1)  # far away: the ray sees only the table
    t = torch.linspace(0.05, 0.4, 64, dtype=F64)[None]
    out = render_rays(field, o, d, t, 1e4, 1.0, table=table)
    t_p = (0.3 + 0.05) / 0.8
    assert float(out.ranges[0, -1].detach()) == pytest.approx(t_p)
    assert float(out.radiance[0, -1].detach()) == pytest.approx(0.5 / math.pi * 0.8 / t_p ** 2)
    # An object in front hides the table.
    blocker = SphereField([0.3 - 0.6 * 0.2, 0.0, 0.3 - 0.8 * 0.2], 0.05)
    hidden = render_rays(blocker, o, d, t, 1e5, 1.0, table=table)
    assert float(hidden.radiance[0, -1].detach()) < 1e-6 * float(out.radiance[0, -1].detach())


def test_renderer_gradients_by_finite_differences():
    o, d = fan(3, 0.2)
    t = torch.linspace(0.25, 0.55, 24, dtype=F64).expand(3, -1)

    class Sphere(SDFField):  # normals by autograd (the generic path), parameters given from outside
        def __init__(self, center, radius):
            super().__init__()
            self.c, self.r = center, radius

        def sdf(self, x):
            return (x - self.c).norm(dim=-1) - self.r

    def f(center, radius, log_s, albedo):
        return render_rays(Sphere(center, radius), o, d, t, torch.exp(log_s), albedo).radiance

    args = (torch.tensor([0.01, -0.02, 0.0], dtype=F64, requires_grad=True),
            torch.tensor(0.1, dtype=F64, requires_grad=True),
            torch.tensor(math.log(60.0), dtype=F64, requires_grad=True),
            torch.tensor(0.8, dtype=F64, requires_grad=True))
    assert torch.autograd.gradcheck(f, args, eps=1e-7, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("preset", ["lcspc-sim", "tmf8820"])
def test_zone_rays_cover_each_zone_with_solid_angle_weights(preset):
    sensor = sensor_preset(preset)
    dirs, w = zone_rays(sensor, 200, jitter=True, generator=torch.Generator().manual_seed(0), dtype=F64)
    assert dirs.shape[:2] == w.shape and dirs.shape[0] == sensor.n_zones
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones_like(w))
    for z, zone in enumerate(sensor.zones):
        assert float(w[z].sum()) == pytest.approx(zone.solid_angle_sr(), rel=1e-9)
        if zone.kind == "cone":
            assert float(dirs[z, :, 2].min()) >= math.cos(zone.half_angle_rad) - 1e-12
        else:
            tx, ty = dirs[z, :, 0] / dirs[z, :, 2], dirs[z, :, 1] / dirs[z, :, 2]
            assert zone.tan_x[0] - 1e-12 <= float(tx.min()) and float(tx.max()) <= zone.tan_x[1] + 1e-12
            assert zone.tan_y[0] - 1e-12 <= float(ty.min()) and float(ty.max()) <= zone.tan_y[1] + 1e-12


def test_stratified_rays_integrate_smooth_functions_accurately():
    sensor = sensor_preset("lcspc-sim")
    dirs, w = zone_rays(sensor, 256, jitter=True, generator=torch.Generator().manual_seed(3), dtype=F64)
    # Integral of cos(theta)^2 over a cone of half-angle a: 2 pi (1 - cos^3 a) / 3.
    a = sensor.zones[0].half_angle_rad
    got = float((w[0] * dirs[0, :, 2] ** 2).sum())
    assert got == pytest.approx(2 * math.pi * (1 - math.cos(a) ** 3) / 3, rel=1e-4)


def test_importance_rays_are_unbiased_when_pi_comes_from_another_look():
    """The balance heuristic is unbiased only for pi independent of the rays it weights. A hard-edged integrand (a
    disc, as a silhouette is) shows it: pi from the same rays weights a cell whose ray hit low (biased low); pi from
    an independent look (the model's: the view's previous render) is unbiased. A smooth integrand hides the bias."""
    sensor = sensor_preset("lcspc-sim")
    grid = ZoneGrid(sensor, 64, dtype=F64)
    axis = torch.tensor([math.sin(0.1), 0.0, math.cos(0.1)], dtype=F64)
    f = lambda d: ((d * axis).sum(-1) > math.cos(0.09)).to(F64)  # noqa: E731  (a disc of 0.09 rad, off-axis)
    exact = 2 * math.pi * (1 - math.cos(0.09))
    gen = torch.Generator().manual_seed(0)
    estimates = {"same rays": [], "another look": []}
    for _ in range(300):
        strat = grid.directions(grid.all_cells(), jitter=True, generator=gen)
        other = grid.directions(grid.all_cells(), jitter=True, generator=gen)
        for name, look in (("same rays", strat), ("another look", other)):
            prob = f(look) + 0.1 * f(look).mean(-1, keepdim=True) + 1e-30  # as the model floors it
            cells = grid.draw_cells(prob, 16, gen)
            extra = grid.directions(cells, jitter=True, generator=gen)
            mw = mixture_weights(grid.cell_weight, prob, 16)
            estimates[name].append(float((mw * f(strat)).sum() + (torch.gather(mw, 1, cells) * f(extra)).sum()))
    (same, other) = (np.array(estimates[k]) for k in ("same rays", "another look"))
    se = lambda e: e.std() / math.sqrt(len(e))  # noqa: E731
    # Unbiased: the mean lies within a few standard errors of the exact solid angle; the same rays fall far short.
    assert abs(other.mean() - exact) < 4 * se(other)
    assert same.mean() < exact - 8 * se(same)


def test_a_ray_with_no_segment_in_the_scene_sees_the_table_through_empty_space():
    """A ray that misses the scene sphere has all its samples at one point; where the (unconstrained) field happens
    to cross zero there, its rounding (rows of a batched MLP differ by ~1e-7) must not become opacity at a sharp s:
    the ray sees the table fully."""

    class Rounding(SDFField):  # a plane through the samples' point, with per-row rounding noise
        def sdf(self, x):
            return x[:, 2] - 0.292 + 1e-7 * (torch.arange(len(x), dtype=x.dtype).remainder(3) - 1)

    table = Table(torch.tensor([0.0, 0.0, 1.0], dtype=F64), torch.tensor(0.0, dtype=F64), torch.tensor(0.5, dtype=F64))
    o = torch.tensor([[0.3, 0.0, 0.3]], dtype=F64)
    d = torch.tensor([[-0.6, 0.0, -0.8]], dtype=F64)
    t = torch.full((1, 16), 0.01, dtype=F64)  # what sphere_interval and stratified give a ray that misses: z 0.292
    out = render_rays(Rounding(), o, d, t, 1e5, 1.0, table=table)  # s at the model's clamp (1e4 / radius)
    assert float(out.transmittance[0].detach()) == 1.0 and float(out.radiance[0, :-1].detach().abs().max()) == 0.0
    assert float(out.radiance[0, -1].detach()) == pytest.approx(0.5 / math.pi * 0.8 / (0.3 / 0.8) ** 2)


def test_samplers_stay_in_the_sphere_and_concentrate_at_the_surface():
    o, d = fan(5, 0.45)
    near, far, hit = sphere_interval(o, d, torch.zeros(3, dtype=F64), 0.15, 0.01)
    assert hit[:4].all() and not hit[4]  # the last ray misses the 0.15 m sphere
    t = stratified(near, far, 32, jitter=True, generator=torch.Generator().manual_seed(0))
    assert torch.all(t[hit] >= near[hit, None]) and torch.all(t[hit] <= far[hit, None])
    assert torch.all(t[:, 1:] >= t[:, :-1])
    field = SphereField([0.0, 0.0, 0.0], 0.1)
    x = o[:, None] + t[..., None] * d[:, None]
    f = field.sdf(x.reshape(-1, 3)).reshape(t.shape).detach()
    extra = importance(t, f, 2000.0, 16, jitter=False)
    t_hit = 0.4 - 0.1  # the axial ray meets the sphere 0.3 m out
    assert float((extra[0] - t_hit).abs().max()) < 2 * float(t[0, 1] - t[0, 0])


class _Plane(SDFField):
    """The plane z = height, the solid beyond it."""

    def __init__(self, height: float):
        super().__init__()
        self.height = height

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return self.height - x[..., 2]


def test_a_surface_nearer_than_a_millimetre_counts_as_at_a_millimetre_as_in_the_simulator():
    """docs/forward_model.md: one floor for the simulator and both presets. The paper renderer's was 0.1 mm, so a
    surface 0.4 mm away returned 3x what the same one 0.7 mm away did; at the 1 mm floor both return alike."""
    o = torch.zeros(1, 3, dtype=F64)
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    t = torch.linspace(0.0, 0.002, 201, dtype=F64)[None]
    near = render_rays(_Plane(0.0004), o, d, t, 1e6, 1.0, create_graph=False)
    far = render_rays(_Plane(0.0007), o, d, t + 0.0003, 1e6, 1.0, create_graph=False)  # the same samples relatively
    near, far = float(near.radiance.detach().sum()), float(far.radiance.detach().sum())
    assert near > 0 and near == pytest.approx(far, rel=1e-9)
    assert MIN_RANGE_M == SIMULATOR_MIN_RANGE_M == 1e-3
