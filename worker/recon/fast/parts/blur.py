"""Blurring the data term's gradient on the grid before the optimiser steps: a Sobolev-type preconditioner.

Each step renders a few thousand rays, and their gradient on the grid is sparse and noisy: stepped as it is, it
roughens the field. Passes of a [1, 2, 1] / 4 filter along each axis make neighbouring nodes move together. Only the
data term's gradient is blurred: the regularisers' gradients are what removes roughness, and a blur would take
exactly that away.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from spadscan.protocol.errors import ConfigError

from .part import Model, Part, PartConfig


@dataclass
class BlurConfig(PartConfig):
    """How far the gradient is blurred."""

    passes: int = 1
    """Passes of the [1, 2, 1] / 4 filter along each axis."""
    physical: bool = False
    """Keep the blur's physical reach on refined levels (4x the passes per 2x refinement: variances add). Off, the
    fine level's blur reaches half as far in metres: on, the lumps go and the normals gain about a degree, but the
    Chamfer loses 0.05 mm on average over the tuning split (the built-in sphere 0.66 -> 0.84 mm, the plant stand
    1.89 -> 2.10; benchmarks/RESULTS.md, "Measured and not adopted")."""

    def check(self, key: str) -> None:
        super().check(key)
        if not (isinstance(self.passes, int) and self.passes >= 1):
            raise ConfigError(f"{key}.passes {self.passes!r} must be an integer >= 1 ({key}.enabled=false: off)")


class GradientBlur(Part):
    """Blurs the data term's gradient (`blur3`)."""

    name = "blur"

    def after_gradient(self, model: Model, grad: torch.Tensor) -> torch.Tensor:
        passes = self.config.passes * (4 ** model.level if self.config.physical else 1)
        return blur3(grad, passes)


def blur3(x: torch.Tensor, passes: int) -> torch.Tensor:
    """`passes` rounds of a [1, 2, 1] / 4 filter along each axis of a grid (1, 1, nz, ny, nx), edges replicated.

    Written as shifted in-place adds rather than conv3d: a 3-tap kernel along one axis is memory-bound, and
    PyTorch's CPU conv3d takes its slow general path for it (4x the time on a 128^3 grid, a quarter of a fine step).
    Returns a new tensor; `x` is not modified.
    """
    if passes < 0:
        raise ValueError(f"blur passes {passes} must be >= 0")
    if x.dim() != 5:
        raise ValueError(f"blur3 expects a grid (1, 1, nz, ny, nx), got shape {tuple(x.shape)}")
    for _ in range(passes):
        for dim in (2, 3, 4):
            n = x.shape[dim]
            out = x * 0.5  # with n == 1 the neighbour adds are empty and both edge adds hit the one node
            out.narrow(dim, 1, n - 1).add_(x.narrow(dim, 0, n - 1), alpha=0.25)  # left neighbour
            out.narrow(dim, 0, 1).add_(x.narrow(dim, 0, 1), alpha=0.25)  # replicated left edge
            out.narrow(dim, 0, n - 1).add_(x.narrow(dim, 1, n - 1), alpha=0.25)  # right neighbour
            out.narrow(dim, n - 1, 1).add_(x.narrow(dim, n - 1, 1), alpha=0.25)  # replicated right edge
            x = out
    return x


__all__ = ["GradientBlur", "BlurConfig", "blur3"]
