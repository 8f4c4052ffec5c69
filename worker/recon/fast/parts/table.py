"""The table under a real object: a plane rendered exactly, with its own albedo and (optionally) a fitted height.

Every zone of a real capture sees the table (docs/sensor_models.md: it is in every histogram), so its return is part of
the forward model, not noise to be explained by the object. Rays that enter the hull see it behind the object, dimmed
by the one-way transmittance (1 - the ray's opacity) through the hull segment; rays that miss the hull see it
directly — all of those are rendered every step (cheap: one plane intersection each), so the table adds no sampling
noise.

When the capture names no table height (a fitted table of a measured capture), `table_height.detect_height` finds a
horizontal one, which starts the fit (problem.py).

Switched off, a scene on a table is fitted without the plane in its forward model; the table still sets the floor
that the hull and the other parts go by.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from spadscan.protocol.errors import ConfigError

from ..sampler import HullRays
from .part import Model, Part, PartConfig

MIN_RANGE_M = 1e-3


class TableModel:
    """The plane normal . x = offset (normal unit, pointing to the free side), learned log albedo and, when
    `fit_offset`, a learned offset. Transients carry albedo / pi x cos / r^2 x sr, like the forward model's."""

    def __init__(self, normal, offset: float, albedo: float, fit_offset: bool, missed: HullRays, forward,
                 device):
        self.normal = torch.as_tensor(np.asarray(normal, float), dtype=torch.float32, device=device)
        self.offset = torch.tensor(float(offset), device=device, requires_grad=fit_offset)
        self.log_albedo = torch.tensor(math.log(albedo), device=device, requires_grad=True)
        self.fit_offset = fit_offset
        self.missed = missed
        self.forward = forward

    def albedo_value(self) -> float:
        return float(torch.exp(self.log_albedo.detach()))

    def hit(self, o: torch.Tensor, d: torch.Tensor):
        """(range (R,), cos (R,), hit (R,) bool) of rays o, d (R, 3) meeting the plane from its free side."""
        nd = d @ self.normal
        t = (self.offset - o @ self.normal) / torch.where(nd < -1e-6, nd, -torch.ones_like(nd))
        hit = (nd < -1e-6) & (t > MIN_RANGE_M)
        return torch.where(hit, t, torch.ones_like(t)), (-nd).clamp(min=0.0), hit

    def returns(self, o: torch.Tensor, d: torch.Tensor, w: torch.Tensor, transmittance: torch.Tensor):
        """Table returns of rays o, d (R, 3) with weights w (R,) sr and one-way transmittance (R,) in front of it:
        (ranges (R,) metres, values (R,))."""
        t, cos, hit = self.hit(o, d)
        value = transmittance * w * cos / (t * t) * (torch.exp(self.log_albedo) / math.pi)
        return t, torch.where(hit, value, torch.zeros_like(value))

    def open_transient(self, hist: torch.Tensor) -> torch.Tensor:
        """Transients (n, n_fine) of the rays of histograms `hist` (n,) that miss the hull (table only)."""
        m = self.missed
        cnt = m.count[hist]
        n = hist.numel()
        if int(cnt.sum()) == 0:
            return torch.zeros(n, self.forward.n_fine, device=hist.device)
        local = torch.arange(n, device=hist.device).repeat_interleave(cnt)
        first = torch.repeat_interleave(m.start[hist] - (torch.cumsum(cnt, 0) - cnt), cnt)
        idx = first + torch.arange(int(cnt.sum()), device=hist.device)
        t, v = self.returns(m.origins[idx], m.dirs[idx], m.weight[idx], torch.ones_like(m.weight[idx]))
        return self.forward.bin(t, v, local, n)

    def summary(self) -> dict:
        z = float(self.offset.detach()) / float(self.normal[2]) if abs(float(self.normal[2])) > 0.99 else None
        return {"table_albedo": self.albedo_value(), "table_offset_m": float(self.offset.detach()),
                "table_normal": self.normal.cpu().tolist(), "table_z_m": z, "table_fitted": self.fit_offset}


@dataclass
class TableConfig(PartConfig):
    """The table's start and learning rate."""

    albedo_init: float = 1.0
    """Initial albedo of the table plane, relative to the sensor model's signal scale."""
    lr_m: float = 2e-4
    """Adam learning rate of a fitted table's height (metres per step); its albedo learns at
    `schedule.albedo_lr`."""

    def check(self, key: str) -> None:
        super().check(key)
        if not (math.isfinite(self.albedo_init) and self.albedo_init > 0):
            raise ConfigError(f"{key}.albedo_init {self.albedo_init} must be > 0")


class TableFit(Part):
    """Holds the `TableModel` that the renderer adds to every histogram, and its parameters for the optimiser."""

    name = "table"

    def __init__(self, config: TableConfig, model: Model):
        super().__init__(config, model)
        normal, offset, fitted = model.problem.table_plane
        self.table = TableModel(normal, offset, config.albedo_init, fitted, model.rays.missed,
                                model.problem.forward, model.device)

    @classmethod
    def left_out(cls, config: TableConfig, model: Model) -> str | None:
        if not model.on_table:
            return "no table under the object"
        return None

    def param_groups(self, albedo_lr: float) -> list[tuple[list[torch.Tensor], float]]:
        """(tensors, learning rate) for the optimiser: the table's log albedo and, when fitted, its offset."""
        groups = [([self.table.log_albedo], albedo_lr)]
        if self.table.fit_offset:
            groups.append(([self.table.offset], self.config.lr_m))
        return groups

    def summary(self) -> dict:
        return self.table.summary()


__all__ = ["TableFit", "TableConfig", "TableModel"]
