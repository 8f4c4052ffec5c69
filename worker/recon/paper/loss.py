"""Loss terms shared by the presets: histogram data terms and SDF regularisers."""

from __future__ import annotations

import torch

from ..forward import TransientForward


def hist_l2(forward: TransientForward, lam: torch.Tensor, counts: torch.Tensor, cycles: torch.Tensor,
            valid: torch.Tensor, scale: float) -> torch.Tensor:
    """The paper's data term: mean over valid bins of ((detections per cycle - counts / cycles) / scale)^2.

    lam, counts, valid: (V, Z, B); cycles (V,). `scale` (a constant of the capture, e.g. the mean peak of
    counts / cycles) only brings the term to order one so that the regulariser weights mean what they say."""
    pred = forward.detections(lam)
    target = counts / cycles[:, None, None]
    err = ((pred - target) / scale) ** 2
    return (err * valid).sum() / valid.sum().clamp_min(1)


def hist_nll(forward: TransientForward, lam: torch.Tensor, counts: torch.Tensor, cycles: torch.Tensor,
             valid: torch.Tensor) -> torch.Tensor:
    """The likelihood data term (`loss.kind` nll): the forward model's deviance (a mean over the histograms that hold
    a valid bin) per valid bin of a view, counted in the batch's view that holds the most. Counted in its first view
    alone, a dropped frame there (no valid bin) made the divisor 1 and that step's loss a thousand times too large."""
    bins = int(valid.flatten(1).sum(-1).max()) if valid.numel() else 0
    return forward.nll(lam, counts, cycles, valid) / max(1, bins)


def eikonal(grad: torch.Tensor) -> torch.Tensor:
    """mean (|grad f| - 1)^2 over gradients (..., 3)."""
    return ((grad.norm(dim=-1) - 1.0) ** 2).mean()


def normal_tv(field, x: torch.Tensor, step_m: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """Total variation of the unit normal: mean |n(x) - n(x + delta)|_1 over points x (N, 3), delta a random offset
    of length step_m (metres). Smooths measured-data reconstructions against noise and unmodelled effects."""
    d = torch.randn(x.shape, generator=generator, dtype=torch.float64).to(x)
    d = step_m * d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    _, g = field.sdf_and_grad(torch.cat([x, x + d]), create_graph=True)
    n = torch.nn.functional.normalize(g, dim=-1, eps=1e-12)
    a, b = n.chunk(2)
    return (a - b).abs().sum(-1).mean()


def hist_scale(counts: torch.Tensor, cycles: torch.Tensor, valid: torch.Tensor, background: torch.Tensor) -> float:
    """Mean over histograms of the peak of (counts / cycles - background): a capture's typical signal per bin
    (> 0), used to normalise the L2 data term."""
    per = (counts / cycles[:, None, None] - background[..., None]) * valid
    return float(per.amax(-1).mean().clamp_min(1e-12))
