"""A minimal Adam for a few tensors.

`torch.optim.Adam` pulls in torch._dynamo on first use, which costs seconds of start-up on a small CPU — a large
share of a 30-second reconstruction. The update is the textbook one (Kingma & Ba), in place, with per-group rates.
"""

from __future__ import annotations

import math

import torch


class Adam:
    """Adam over groups [(tensors, lr), ...]; `step()` reads each tensor's .grad.

    shared=True (per tensor) replaces the per-element second moment by one scalar, the mean square of the tensor's
    non-zero gradient entries: updates then stay proportional to each element's gradient. This is what a grid
    touched by a few thousand rays per step needs: plain Adam gives a node that a ray grazed once the same full
    step as a node on a well-observed surface, and the grid crumples into floaters.
    """

    def __init__(self, groups, betas=(0.9, 0.99), eps: float = 1e-12, shared: tuple[bool, ...] | None = None):
        self.groups = [(list(params), float(lr)) for params, lr in groups]
        self.b1, self.b2 = betas
        self.eps = eps
        self.t = 0
        self.shared = tuple(shared) if shared is not None else (False,) * len(self.groups)
        self.state = {}
        for (ps, _), sh in zip(self.groups, self.shared):
            for p in ps:
                self.state[id(p)] = (torch.zeros_like(p), torch.zeros((), device=p.device, dtype=p.dtype) if sh
                                     else torch.zeros_like(p))

    def zero_grad(self) -> None:
        for ps, _ in self.groups:
            for p in ps:
                p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        self.t += 1
        c1 = 1.0 - self.b1 ** self.t
        c2 = 1.0 - self.b2 ** self.t
        for (ps, lr), sh in zip(self.groups, self.shared):
            for p in ps:
                if p.grad is None:
                    continue
                m, v = self.state[id(p)]
                g = torch.nan_to_num(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
                m.mul_(self.b1).add_(g, alpha=1.0 - self.b1)
                if sh:
                    sq = g * g
                    nz = (sq > 0).sum().clamp(min=1)
                    v.mul_(self.b2).add_(sq.sum() / nz, alpha=1.0 - self.b2)
                else:
                    v.mul_(self.b2).addcmul_(g, g, value=1.0 - self.b2)
                # sqrt(v + eps^2) rather than sqrt(v) + eps: the same where it matters (v >> eps^2), and the square
                # root of the exact zeros of never-touched nodes is several times slower on CPU than of a normal number.
                denom = (v / c2).add_(self.eps * self.eps).sqrt_()
                p.addcdiv_(m, denom, value=-lr / c1)

    def set_lr(self, group: int, lr: float) -> None:
        params, _ = self.groups[group]
        if not (math.isfinite(lr) and lr >= 0):
            raise ValueError(f"learning rate {lr} must be finite and >= 0")
        self.groups[group] = (params, float(lr))


__all__ = ["Adam"]
