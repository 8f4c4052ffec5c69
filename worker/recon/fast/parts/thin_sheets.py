"""Emptying thin curtains that stand on the table: what the empty-space push leaves of the carved hull's skirt.

Views from above see a vertical sheet edge on, and within a pulse width of the table no histogram tells a sheet from
the table behind it, so nothing in the data removes one. Every few steps of the last level, on a scene on a table,
solid sheets thinner than about twice `voxels` nodes and less than `band_m` above the table are emptied (a
morphological opening). On LCSPCData's real pyramid a fifth of the surface lay 1-3 cm outside the object, in curtains
up to 8 cm high.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from spadscan.protocol.errors import ConfigError

from ..grid_ops import node_heights
from .part import Model, Part, PartConfig


@dataclass
class ThinSheetsConfig(PartConfig):
    """Which sheets are emptied, where, and how often."""

    voxels: int = 2
    """Sheets thinner than about twice this many voxels are emptied."""
    band_m: float = 0.09
    """Height (metres) above the table within which thin sheets are emptied. A band of one pulse width (41 mm) left
    the real pyramid's curtains standing; 12 cm began to erode the object itself (benchmarks/RESULTS.md)."""
    every_steps: int = 10
    """Steps of the last level between passes (its first step makes one)."""

    def check(self, key: str) -> None:
        super().check(key)
        if not (isinstance(self.voxels, int) and self.voxels >= 1):
            raise ConfigError(f"{key}.voxels {self.voxels!r} must be an integer >= 1 ({key}.enabled=false: off)")
        if not 0.0 <= self.band_m <= 1.0:  # also refuses NaN
            raise ConfigError(f"{key}.band_m {self.band_m} must be in [0, 1] metres")
        if not (isinstance(self.every_steps, int) and self.every_steps >= 1):
            raise ConfigError(f"{key}.every_steps {self.every_steps!r} must be an integer >= 1")


class ThinSheets(Part):
    """Empties thin sheets near the table at the start of every `every_steps`-th step of the last level."""

    name = "thin_sheets"

    def __init__(self, config: ThinSheetsConfig, model: Model):
        super().__init__(config, model)
        self.emptied_nodes = 0

    @classmethod
    def left_out(cls, config: ThinSheetsConfig, model: Model) -> str | None:
        if not model.on_table or model.problem.floor_z is None:
            return "no table under the object: the data see thin parts standing on the floor"
        return None

    def before_step(self, model: Model) -> None:
        if model.last_level and model.level_steps % self.config.every_steps == 0:
            self.empty(model)

    def empty(self, model: Model) -> None:
        """Empty the thin sheets near the table of the model's grid now."""
        field = model.field
        sdf = field.sdf.detach()[0, 0]
        z = node_heights(sdf.shape[0], float(field.origin[2]), field.voxel)
        thin = thin_near_table((sdf < 0).cpu().numpy(), z, model.problem.floor_z, self.config.band_m,
                               self.config.voxels)
        if thin.any():
            self.emptied_nodes += int(thin.sum())
            with torch.no_grad():
                sdf[torch.as_tensor(thin, device=sdf.device)] = 0.5 * field.voxel

    def summary(self) -> dict:
        return {"emptied_nodes": self.emptied_nodes}


def thin_near_table(solid: np.ndarray, z_nodes: np.ndarray, floor_z: float, band_m: float, radius: int) -> np.ndarray:
    """(nz, ny, nx) bool: the solid nodes less than `band_m` above the table (at floor_z) that a morphological opening
    of `radius` node steps removes — sheets and fins thinner than about 2 x radius nodes. z_nodes (nz,): heights of
    the node rows, metres, increasing; the space under the table counts as solid, so the object's base is not eroded
    from below.

    Near the table the histograms cannot tell a thin sheet from the table behind it, and views from above see a
    vertical sheet edge on: such curtains are what the carved hull's skirt melts into, and nothing in the data
    removes them (on LCSPCData's real pyramid, a fifth of the surface lay 1-3 cm outside the object, in curtains up
    to 8 cm high; `parts.thin_sheets.band_m` sets band_m)."""
    out = np.zeros(solid.shape, bool)
    z = np.asarray(z_nodes, np.float64)
    in_band = (z >= floor_z) & (z < floor_z + band_m)
    if radius <= 0 or not in_band.any():
        return out
    # The opening reaches 2 x radius rows: a slab that far above the band gives exact answers inside it.
    top = min(len(z), int(np.flatnonzero(in_band)[-1]) + 2 * radius + 2)
    wall = solid[:top] | (z[:top] < floor_z)[:, None, None]
    cross = ndimage.generate_binary_structure(3, 1)
    opened = ndimage.binary_opening(wall, structure=cross, iterations=radius)
    out[:top] = solid[:top] & ~opened & in_band[:top, None, None]
    return out


__all__ = ["ThinSheets", "ThinSheetsConfig", "thin_near_table"]
