"""Filling what no view can see into: pockets closed by the solid, and on a table the space under the object.

Every few steps, every empty pocket closed by the solid (and the floor) is made solid: no sensor outside sees into
one, so nothing in the data holds the nodes around it. Without this, bubbles grew inside the dataset's soap after
~3,000 steps (Chamfer 1.8 mm -> 8.7 mm by 180 s on an idle machine), and on a table the empty-space push hollowed
the object out.

On a table (with `under_overhangs`), the space between the solid and the table is filled first, as the mesh is:
every view looks from above. A hollow that a hole opens to the outside is no pocket: on LCSPCData's real pyramid the
fit became a shell, hollow inside and open near the table. The mesh filled the hollow from the top down, but not
under the pinholes in the shell: shafts down to the table, 1-2 cm off the object's faces (step-based, two threads:
5.27 mm after 3,400 steps; with this fill, 4.45 mm after 2,400; filled in the mesh alone 5.27 mm against 4.37 mm
in the 300 s benchmark, benchmarks/RESULTS.md).

Space under an overhang is hidden only when the solid closes it in: where a gap wider than about twice
`open_width_m` opens it to the side, the views from the side see into it, and it stays as the fit leaves it
(`grid_ops.open_to_outside`). Filling it all made a simulated head on a can (TMF8820, 120 views, on a table) a
pillar as wide as the head down to the table: 19.25 mm, 0.98 mm with the gap rule (step-based, one thread, seed 0);
a tall block 3.85 -> 0.89 mm (its carved skirt was filled); the real pyramid, whose hollow opens through pinholes,
4.41 -> 4.48 and its jittered twin 4.49 -> 4.53 (both 8.9 mm with no fill under the solid at all).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from spadscan.protocol.errors import ConfigError

from ...config import check_in_range
from ..grid_ops import below_floor, cavities, node_heights, open_nodes, under_overhangs
from .part import Model, Part, PartConfig


@dataclass
class CavitiesConfig(PartConfig):
    """How often hidden space is filled, and whether the space under the object on a table counts."""

    every_steps: int = 10
    """Steps of a level between fills (the first step of each level fills)."""
    under_overhangs: bool = True
    """Scenes on a table: also fill the space between the object's underside and the table, in the fit and in the
    mesh (`grid_ops.under_overhangs`)."""
    open_width_m: float = 0.01
    """...except space under an overhang that a gap more than twice this wide (metres) opens to the side: views
    from the side see into it (`grid_ops.open_to_outside`; 0: fill it all)."""

    def check(self, key: str) -> None:
        super().check(key)
        if not (isinstance(self.every_steps, int) and self.every_steps >= 1):
            raise ConfigError(f"{key}.every_steps {self.every_steps!r} must be an integer >= 1")
        check_in_range(f"{key}.open_width_m", self.open_width_m, 0.0, 0.2,
                       hint="0: fill all the space under the object")


class Cavities(Part):
    """Fills closed pockets (and, on a table, the space under overhangs) at the start of every `every_steps`-th step
    of a level, then projects the field back into the hull."""

    name = "cavities"

    def __init__(self, config: CavitiesConfig, model: Model):
        super().__init__(config, model)
        self.filled_nodes = 0

    def fills_under(self, model: Model) -> bool:
        """Whether the space under the object is filled (in the fit and in the mesh): a scene on a table."""
        return self.config.under_overhangs and model.on_table and model.problem.floor_z is not None

    def before_step(self, model: Model) -> None:
        if model.level_steps % self.config.every_steps == 0:
            self.fill(model)

    def fill(self, model: Model) -> None:
        """Fill the hidden space of the model's grid now, and project the field back into the hull."""
        field = model.field
        sdf = field.sdf.detach()[0, 0]
        solid = (sdf < 0).cpu().numpy()
        below = below_floor(solid.shape, float(field.origin[2]), field.voxel, model.problem.floor_z)
        fill = np.zeros_like(solid)
        if self.fills_under(model):
            z = node_heights(solid.shape[0], float(field.origin[2]), field.voxel)
            fill = under_overhangs(solid, z, model.problem.floor_z, open_nodes(self.config.open_width_m, field.voxel))
        fill |= cavities(solid | fill, below)
        if fill.any():
            self.filled_nodes += int(fill.sum())
            with torch.no_grad():
                sdf[torch.as_tensor(fill, device=sdf.device)] = -0.5 * field.voxel
            model.project()

    def summary(self) -> dict:
        return {"filled_nodes": self.filled_nodes}


__all__ = ["Cavities", "CavitiesConfig"]
