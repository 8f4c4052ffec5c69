"""Rendering hull-segment samples of a grid SDF into per-ray returns (range, radiance), NeuS-style.

Opacity between consecutive samples follows NeuS with a *fixed* sharpness s (1/metres): with Phi = sigmoid(s * sdf),
alpha_i = clamp((Phi_i - Phi_{i+1}) / Phi_i, 0, 1), and a section's weight is the probability that the first surface
lies in it, alpha_i T_i with T_i = prod_{j<i} (1 - alpha_j) (see `section_weights` for why not the round trip). Each section's return is placed at the zero crossing of the
linear interpolation between its end samples (where the SDF falls through zero inside it) rather than at its middle:
this makes the arrival time, which the histograms measure to a fraction of a millimetre, a smooth function of the
grid values even when samples are several millimetres apart. Shading is Lambertian: |n . d| at the ray's expected
surface point, with n from central differences of the field.
"""

from __future__ import annotations

import torch


def section_weights(sdf: torch.Tensor, sharpness: float) -> torch.Tensor:
    """NeuS weights: the probability that the first surface along the ray lies in each section.
    sdf (R, S) -> weights (R, S - 1), each in [0, 1], summing to 1 - T_end (1 for an opaque crossing).

    One-way, alpha_i T_i with T_i = prod_{j<i} (1 - alpha_j), on purpose. The round-trip form of a participating
    medium, T_i^2 - T_{i+1}^2, weights each section by how much light also survives the way back, which pulls the
    mean return a whole 1/s towards the sensor (the mean of the larger of two logistic variables): every surface
    would be fitted 1/s too far from the sensor, i.e. the object 1/s too small (measured: -1.1 mm on the dataset's
    sphere at s = 2 / 2.1 mm). NeuS's one-way weights peak on the zero crossing; light that reaches the surface
    returns from it.
    """
    phi = torch.sigmoid(sdf * sharpness)
    alpha = ((phi[:, :-1] - phi[:, 1:]) / phi[:, :-1].clamp(min=1e-6)).clamp(0.0, 1.0)
    # Transmittance in log space: a long product of (1 - alpha) stays finite and keeps its gradient.
    log_keep = torch.log1p(-alpha.clamp(max=1.0 - 1e-6))
    log_t = torch.cumsum(log_keep, dim=1) - log_keep
    return alpha * torch.exp(log_t)


def section_ranges(t: torch.Tensor, sdf: torch.Tensor) -> torch.Tensor:
    """Where each section's return sits: the interpolated zero crossing when the SDF falls through zero inside it,
    otherwise its end nearer the (would-be) surface. t, sdf (R, S) -> (R, S - 1) metres."""
    f0, f1 = sdf[:, :-1], sdf[:, 1:]
    t0, t1 = t[:, :-1], t[:, 1:]
    drop = f0 - f1
    safe = torch.where(drop > 1e-9, drop, torch.ones_like(drop))
    frac = torch.where(drop > 1e-9, f0 / safe, torch.full_like(drop, 0.5)).clamp(0.0, 1.0)
    return t0 + frac * (t1 - t0)


def lambert_cos(field_sdf, points: torch.Tensor, dirs: torch.Tensor, step_m: float) -> torch.Tensor:
    """|n . d| at points (R, 3) seen along dirs (R, 3), n the normalised central-difference gradient of field_sdf.

    field_sdf: callable points (..., 3) -> (...). Returns (R,) in [0, 1].
    """
    eye = torch.eye(3, device=points.device, dtype=points.dtype) * step_m
    probe = torch.cat([points[:, None] + eye[None], points[:, None] - eye[None]], dim=1)  # (R, 6, 3)
    v = field_sdf(probe)
    grad = v[:, :3] - v[:, 3:]
    n = torch.nn.functional.normalize(grad, dim=-1, eps=1e-9)
    return (n * dirs).sum(-1).abs().clamp(0.0, 1.0)


def render_returns(field_sdf, origins: torch.Tensor, dirs: torch.Tensor, t: torch.Tensor, ray_weight: torch.Tensor,
                   sharpness: float, normal_step_m: float):
    """Returns of R rays sampled at t (R, S).

    field_sdf: callable points (..., 3) -> SDF (...); origins, dirs (R, 3); ray_weight (R,) steradians.
    Returns (ranges (R, S - 1) metres, radiance (R, S - 1) = weight * cos * ray_weight / range^2 in sr/m^2,
    opacity (R,) total weight per ray).
    """
    pts = origins[:, None] + t[..., None] * dirs[:, None]
    sdf = field_sdf(pts)
    w = section_weights(sdf, sharpness)
    r = section_ranges(t, sdf)
    opacity = w.sum(dim=1)
    t_hit = (w * r).sum(dim=1) / opacity.clamp(min=1e-6)
    t_hit = torch.where(opacity > 1e-6, t_hit, t[:, -1])
    cos = lambert_cos(field_sdf, origins + t_hit[:, None] * dirs, dirs, normal_step_m)
    radiance = w * (cos * ray_weight)[:, None] / (r * r).clamp(min=1e-6)
    return r, radiance, opacity


__all__ = ["section_weights", "section_ranges", "lambert_cos", "render_returns"]
