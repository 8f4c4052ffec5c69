"""A minimal Adam for a few tensors.

`torch.optim.Adam` pulls in torch._dynamo on first use, which costs seconds of start-up on a small CPU — a large
share of a 30-second reconstruction. The update is the textbook one (Kingma & Ba), in place, with per-group rates.
"""

from __future__ import annotations

import math

import torch


class Adam:
    """Adam over groups [(tensors, lr), ...]; `step()` reads each tensor's .grad.

    floor (one per group, default 0): each element's second moment is taken as at least this many times the mean
    second moment of the tensor's elements touched so far (those with a gradient at some step). Plain Adam (0) gives
    an element the same full step whatever the size of its gradient: a grid node that a ray grazed now and then
    moves as far as one on a well-observed surface, and on a surface that few rays fix the noise of the sampled
    rays' gradients moves the grid as far as the signal. With a floor of 1, elements whose gradients are smaller
    than the tensor's typical one step in proportion to them, and the well-observed ones as plain Adam does.
    """

    def __init__(self, groups, betas=(0.9, 0.99), eps: float = 1e-12, floor: tuple[float, ...] | None = None):
        self.groups = [(list(params), float(lr)) for params, lr in groups]
        self.b1, self.b2 = betas
        self.eps = eps
        self.t = 0
        self.floor = tuple(float(f) for f in floor) if floor is not None else (0.0,) * len(self.groups)
        if len(self.floor) != len(self.groups) or not all(math.isfinite(f) and f >= 0 for f in self.floor):
            raise ValueError(f"floor {floor} must give one finite number >= 0 per group")
        self.state = {}
        for ps, _ in self.groups:
            for p in ps:
                self.state[id(p)] = (torch.zeros_like(p), torch.zeros_like(p))

    def zero_grad(self) -> None:
        for ps, _ in self.groups:
            for p in ps:
                p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        self.t += 1
        c1 = 1.0 - self.b1 ** self.t
        c2 = 1.0 - self.b2 ** self.t
        for (ps, lr), floor in zip(self.groups, self.floor):
            for p in ps:
                if p.grad is None:
                    continue
                m, v = self.state[id(p)]
                g = torch.nan_to_num(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
                m.mul_(self.b1).add_(g, alpha=1.0 - self.b1)
                v.mul_(self.b2).addcmul_(g, g, value=1.0 - self.b2)
                denom = v / c2
                if floor > 0:
                    touched = (denom > 0).sum().clamp(min=1)
                    denom.clamp_min_(denom.sum() * floor / touched)
                # sqrt(v + eps^2) rather than sqrt(v) + eps: the same where it matters (v >> eps^2), and the square
                # root of the exact zeros of never-touched nodes is several times slower on CPU than of a normal number.
                denom.add_(self.eps * self.eps).sqrt_()
                p.addcdiv_(m, denom, value=-lr / c1)

    def set_floor(self, group: int, floor: float) -> None:
        if not (math.isfinite(floor) and floor >= 0):
            raise ValueError(f"floor {floor} must be finite and >= 0")
        self.floor = self.floor[:group] + (float(floor),) + self.floor[group + 1:]

    def set_lr(self, group: int, lr: float) -> None:
        params, _ = self.groups[group]
        if not (math.isfinite(lr) and lr >= 0):
            raise ValueError(f"learning rate {lr} must be finite and >= 0")
        self.groups[group] = (params, float(lr))


__all__ = ["Adam"]
