"""NeuS-style volume rendering of a signed distance field along rays, for a co-located light and sensor.

Between consecutive samples i and i+1 on a ray the opacity is `alpha_i = 1 - Phi(s f_{i+1}) / Phi(s f_i)` clamped to
[0, 1] (Phi the logistic sigmoid, f the SDF, s the sharpness in 1/metres), computed as
`-expm1(logsigmoid(s f_{i+1}) - logsigmoid(s f_i))` so that it stays finite for any s. Light travels out and back,
so the transmittance is the round trip `T_i = prod_{j<i} (1 - alpha_j)^2`. A Lambertian surface lit from the sensor
returns `alpha_i T_i (albedo / pi) max(-cos_i, 0) / t_i^2` per unit solid angle, at the interval's mid-range t_i, with
cos_i between the ray and the SDF's normal (the normalised mean of the gradients at both ends).

A table plane, when given, is rendered exactly: its hit at range t_p returns `T(t_p) (albedo_t / pi) (-n . d) / t_p^2`,
appended as one more column; the caller places every sample before t_p.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from spadscan.protocol.simulator import MIN_RANGE_M

# MIN_RANGE_M: ranges are floored there before 1/r^2 (a sample on the sensor itself stays finite); the simulator's
# own floor (1 mm, docs/forward_model.md), so that both see a surface that close alike.


class SDFField(torch.nn.Module):
    """A signed distance field in world coordinates (metres; negative inside)."""

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance (N,) at points x (N, 3)."""
        raise NotImplementedError

    def sdf_and_grad(self, x: torch.Tensor, create_graph: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """(sdf (N,), gradient (N, 3)) at x (N, 3); by autograd unless a field overrides it. With create_graph the
        gradient itself can be differentiated (Eikonal term, normals in the radiance)."""
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            f = self.sdf(xg)
            (g,) = torch.autograd.grad(f.sum(), xg, create_graph=create_graph)
        return f, g


class SphereField(SDFField):
    """An analytic sphere: |x - center| - radius (learnable centre and radius)."""

    def __init__(self, center, radius: float, dtype=torch.float64):
        super().__init__()
        self.center = torch.nn.Parameter(torch.as_tensor(center, dtype=dtype).clone())
        self.radius = torch.nn.Parameter(torch.tensor(float(radius), dtype=dtype))

    def sdf(self, x):
        return (x - self.center).norm(dim=-1) - self.radius

    def sdf_and_grad(self, x, create_graph=True):
        d = x - self.center
        r = d.norm(dim=-1)
        return r - self.radius, d / r.clamp_min(1e-12)[:, None]


class Table(NamedTuple):
    """The plane normal . x = offset (normal (3,) unit, pointing to the free side) and its albedo (tensors)."""

    normal: torch.Tensor
    offset: torch.Tensor
    albedo: torch.Tensor


class Rendered(NamedTuple):
    """What render_rays returns. R rays, S samples, P = S - 1 intervals (+1 with a table)."""

    ranges: torch.Tensor
    """(R, P) one-way range of each return, metres."""
    radiance: torch.Tensor
    """(R, P) returned radiance per unit solid angle (albedo / pi x cos / r^2 x opacity x transmittance)."""
    sdf: torch.Tensor
    """(R, S) the field at the samples."""
    grad: torch.Tensor
    """(R, S, 3) its gradient there (for the Eikonal term)."""
    transmittance: torch.Tensor
    """(R,) round-trip transmittance past the last sample."""


def table_hit(origins: torch.Tensor, dirs: torch.Tensor, table: Table) -> torch.Tensor:
    """Range (R,) at which each ray meets the table plane from its free side; +inf where it never does."""
    nd = dirs @ table.normal
    t = (table.offset - origins @ table.normal) / torch.where(nd < 0, nd, -torch.ones_like(nd))
    return torch.where((nd < -1e-9) & (t > 0), t, torch.full_like(t, float("inf")))


def opacity(f: torch.Tensor, s: torch.Tensor | float) -> torch.Tensor:
    """NeuS opacity (..., S-1) between consecutive samples of the SDF f (..., S) at sharpness s (1/metres)."""
    ls = F.logsigmoid(s * f)
    return (-torch.expm1((ls[..., 1:] - ls[..., :-1]).clamp(max=0.0))).clamp(0.0, 1.0)


def round_trip_transmittance(alpha: torch.Tensor) -> torch.Tensor:
    """T_i = prod_{j<i} (1 - alpha_j)^2 (..., P+1), including the value past the last interval."""
    keep = (1.0 - alpha) ** 2
    ones = torch.ones_like(keep[..., :1])
    return torch.cumprod(torch.cat([ones, keep], dim=-1), dim=-1)


def render_rays(field: SDFField, origins: torch.Tensor, dirs: torch.Tensor, t_samples: torch.Tensor,
                s: torch.Tensor | float, albedo: torch.Tensor | float, *, table: Table | None = None,
                create_graph: bool = True) -> Rendered:
    """Render R rays from origins (R, 3) along unit dirs (R, 3) at sorted ranges t_samples (R, S), S >= 2.

    s: opacity sharpness (1/metres); albedo: the field's Lambertian albedo (scalar, or (R, S) per sample).
    """
    r, n = t_samples.shape
    x = origins[:, None, :] + t_samples[..., None] * dirs[:, None, :]
    f, g = field.sdf_and_grad(x.reshape(-1, 3), create_graph=create_graph)
    f, g = f.reshape(r, n), g.reshape(r, n, 3)
    # A zero-length interval holds no matter. A ray with no segment in the scene sphere has all its samples at one
    # point; the field there differs between rows by rounding (~1e-7 in float32), which a sharp s would turn into
    # opacity: mask it, so that such a ray sees the table through empty space with a transmittance of exactly 1.
    alpha = opacity(f, s)
    alpha = torch.where(t_samples[:, 1:] > t_samples[:, :-1], alpha, torch.zeros_like(alpha))
    trans = round_trip_transmittance(alpha)
    normal = F.normalize(g[:, 1:] + g[:, :-1], dim=-1, eps=1e-12)
    facing = (-(normal * dirs[:, None, :]).sum(-1)).clamp_min(0.0)
    t_mid = 0.5 * (t_samples[:, 1:] + t_samples[:, :-1])
    rho = albedo if not torch.is_tensor(albedo) or albedo.ndim == 0 else 0.5 * (albedo[:, 1:] + albedo[:, :-1])
    radiance = alpha * trans[:, :-1] * (rho / torch.pi) * facing / t_mid.clamp_min(MIN_RANGE_M) ** 2
    ranges = t_mid
    if table is not None:
        tp = table_hit(origins, dirs, table)
        hit = torch.isfinite(tp)
        tp_safe = torch.where(hit, tp, torch.ones_like(tp))
        cos_t = (-(dirs @ table.normal)).clamp_min(0.0)
        rad_t = trans[:, -1] * (table.albedo / torch.pi) * cos_t / tp_safe.clamp_min(MIN_RANGE_M) ** 2
        radiance = torch.cat([radiance, torch.where(hit, rad_t, torch.zeros_like(rad_t))[:, None]], dim=1)
        ranges = torch.cat([ranges, tp_safe[:, None]], dim=1)
    return Rendered(ranges, radiance, f, g, trans[:, -1])
