"""The paper's field: an MLP on positionally encoded points, initialised as a sphere (geometric initialisation).

Points are first mapped into the scene sphere's frame, x_n = (x - center) / radius, so that the network sees the
unit ball whatever the scene's size; the SDF it returns is scaled back to metres (f = radius * mlp(x_n)), which keeps
|grad f| = 1 meaningful in world units.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..errors import ReconstructionError
from .render import SDFField
from .config import MLPFieldConfig


def encode(x: torch.Tensor, frequencies: int) -> torch.Tensor:
    """Positional encoding (N, 3) -> (N, 3 + 6 * frequencies): x, then sin(2^k x), cos(2^k x) for k < frequencies."""
    if frequencies == 0:
        return x
    scales = 2.0 ** torch.arange(frequencies, dtype=x.dtype, device=x.device)
    xs = (x[:, None, :] * scales[:, None]).reshape(x.shape[0], -1)
    return torch.cat([x, torch.sin(xs), torch.cos(xs)], dim=-1)


class MLPField(SDFField):
    """SDF (metres) = radius * MLP(encode((x - center) / radius)); 8 x 256 with a skip at layer 4 by default."""

    def __init__(self, cfg: MLPFieldConfig, center: torch.Tensor, radius: float):
        super().__init__()
        self.cfg = cfg
        self.register_buffer("center", torch.as_tensor(center).detach().clone())
        self.radius = float(radius)
        d_in = 3 + 6 * cfg.frequencies
        if cfg.layers < 1 or (cfg.skip_layers and cfg.width <= d_in) or any(
                not 0 < k <= cfg.layers for k in cfg.skip_layers):
            raise ReconstructionError(f"MLP field: {cfg.layers} layers of width {cfg.width} with skips at "
                                      f"{list(cfg.skip_layers)} cannot hold the {d_in}-wide encoding (skip layers must "
                                      f"lie in 1..layers and the width must exceed {d_in})")
        dims = [d_in] + [cfg.width] * cfg.layers + [1]
        self.skips = set(cfg.skip_layers)
        self.linears = nn.ModuleList()
        for i in range(len(dims) - 1):
            out = dims[i + 1] - d_in if (i + 1) in self.skips else dims[i + 1]
            lin = nn.Linear(dims[i], out)
            self._geometric_init(lin, i, len(dims) - 2, d_in, out)
            if cfg.weight_norm:
                lin = nn.utils.parametrizations.weight_norm(lin)
            self.linears.append(lin)
        self.act = nn.Softplus(beta=cfg.softplus_beta)

    def _geometric_init(self, lin: nn.Linear, i: int, last: int, d_in: int, out: int) -> None:
        """Weights that make the initial network close to the SDF of a sphere of radius init_radius (unit frame):
        the last layer averages the features (mean sqrt(pi / width)) minus the radius; encoded inputs start at
        zero weight so that the start is smooth."""
        with torch.no_grad():
            if i == last:
                nn.init.normal_(lin.weight, mean=math.sqrt(math.pi) / math.sqrt(lin.in_features), std=1e-4)
                nn.init.constant_(lin.bias, -self.cfg.init_radius)
                return
            nn.init.constant_(lin.bias, 0.0)
            nn.init.normal_(lin.weight, 0.0, math.sqrt(2) / math.sqrt(out))
            if i == 0 and self.cfg.frequencies > 0:
                lin.weight[:, 3:] = 0.0
            elif i in self.skips and self.cfg.frequencies > 0:
                lin.weight[:, -(d_in - 3):] = 0.0

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        xn = (x - self.center.to(x.dtype)) / self.radius
        e = encode(xn, self.cfg.frequencies)
        h = e
        for i, lin in enumerate(self.linears):
            if i in self.skips:
                h = torch.cat([h, e], dim=-1) / math.sqrt(2)
            h = lin(h)
            if i < len(self.linears) - 1:
                h = self.act(h)
        return self.radius * h[:, 0]
