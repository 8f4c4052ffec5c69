"""Surface that no ray reaches: the air side of it relaxed towards its neighbours, as smooth as what is round it.

Some of an object's surface lies where no view looks. The dataset's views look at the floor under the object with a
15-degree cone; under the built-in plant stand's top (13 cm square, 15 mm thick, 16.5 cm above the floor) the centre
of the underside is 18-19 degrees off the axis of every view low enough to look up at it. No ray of the model reaches
it, and its data gradient is nil: over 200 steps of the fine level its root mean square was under a thousandth of the
surface's median (the top face 0.87, the legs 1.16). 11.6 % of the plant stand's surface nodes are under 0.01 of it
and 12.7 % under 0.1: the unseen nodes stand clearly apart. Nothing but the regularisers moves such surface, and with
the Adam floor (`schedule.adam_floor`) they move it little: the shreds and lumps that the coarse level and the
openings left there stay.

So on the last level, once the data gradient's moving average has settled (`after_steps`), every node within
`band_voxels` of the surface on its air side (a positive value) whose data gradient's moving average (of the square,
decay `decay`, after the blur) is below `threshold` times the mean over the nodes near the surface is relaxed
towards the mean of its six neighbours: `iterations` Jacobi iterations a step, with the weight `alpha` (the nodes
are found again every `refresh_steps` steps). A plane's distance is the mean of its neighbours', so a flat surface
stays; an unseen lump or shred loses the air-side margin round its solid nodes and thins towards them; a dent comes
down a little (what the solid side holds does not move, and the dent's shape is in it: the plant stand's underside
stays where an opening left it). The surface round it that the data holds is the edge it meets.

Only the air side: relaxed on both sides, a thin part's inside rises towards its neighbours' values and the part
thins (the plant stand's top from 9 to 6 mm; 2.26 -> 2.48 mm). Both ways on the air side: relaxing it only where that
raises a value (a shrink) cost the demo goblet 0.86 -> 1.32 mm, only where that lowers one (a growth) the chair 1.79
-> 2.28 (benchmarks/RESULTS.md has what it buys and costs on every scene). On a table the part does not run: the
empty-space push already acts on the surface that few views look at, and with both, the real pyramid, its jittered
twin, the simulated head on a can and the tall block came out 0.01-0.09 mm worse.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from spadscan.protocol.errors import ConfigError

from ..regularizers import band_nodes
from .part import Model, Part, PartConfig, StepRecord


@dataclass
class UnseenConfig(PartConfig):
    """Which nodes count as unseen, and how hard they are relaxed."""

    threshold: float = 0.01
    """A node is unseen where its data gradient's moving average (of the square) is below this fraction of the mean
    over the nodes near the surface."""
    decay: float = 0.98
    """Decay per step of the moving average of the data gradient's square (about 50 steps)."""
    after_steps: int = 100
    """Steps of the moving average before any relaxing: it starts afresh with the last level (or with the model,
    where that is warm-started)."""
    band_voxels: float = 3.0
    """Nodes within this many voxels of the surface (air side) can be relaxed."""
    iterations: int = 4
    """Jacobi iterations per step."""
    alpha: float = 0.5
    """Weight of the neighbours' mean in each iteration (1: the mean replaces the value)."""
    refresh_steps: int = 10
    """Steps between finding the unseen nodes afresh."""

    def check(self, key: str) -> None:
        super().check(key)
        if not 0 < self.threshold < 1:
            raise ConfigError(f"{key}.threshold {self.threshold} must be in (0, 1)")
        if not 0 < self.decay < 1:
            raise ConfigError(f"{key}.decay {self.decay} must be in (0, 1)")
        if not (isinstance(self.after_steps, int) and self.after_steps >= 0):
            raise ConfigError(f"{key}.after_steps {self.after_steps!r} must be an integer >= 0")
        if not self.band_voxels > 0:
            raise ConfigError(f"{key}.band_voxels {self.band_voxels} must be > 0")
        if not (isinstance(self.iterations, int) and self.iterations >= 1):
            raise ConfigError(f"{key}.iterations {self.iterations!r} must be an integer >= 1 ({key}.enabled=false: "
                              f"off)")
        if not 0 < self.alpha <= 1:
            raise ConfigError(f"{key}.alpha {self.alpha} must be in (0, 1]")
        if not (isinstance(self.refresh_steps, int) and self.refresh_steps >= 1):
            raise ConfigError(f"{key}.refresh_steps {self.refresh_steps!r} must be an integer >= 1")


class UnseenRelaxation(Part):
    """Keeps the moving average of the data gradient's square on the last level (after the blur) and relaxes the
    unseen nodes after each step."""

    name = "unseen"

    def __init__(self, config: UnseenConfig, model: Model):
        super().__init__(config, model)
        self.seen: torch.Tensor | None = None
        """Moving average of the data gradient's square per node, (nz, ny, nx); None before the last level."""
        self.samples = 0
        """Gradients in `seen` so far: a model warm-started late in its last level (a live refit) waits for
        `after_steps` of its own, not the level's count."""
        self.nodes: torch.Tensor | None = None
        self.relaxed_nodes = 0

    @classmethod
    def left_out(cls, config: UnseenConfig, model: Model) -> str | None:
        if model.on_table:
            return ("a scene on a table: the empty-space push decides the surface that few views look at (relaxed "
                    "as well, four table scenes came out 0.01-0.09 mm worse)")
        return None

    def on_refine(self, model: Model) -> None:
        self.seen, self.nodes, self.samples = None, None, 0

    def on_jump(self, model: Model) -> None:
        self.nodes = None

    def after_gradient(self, model: Model, grad: torch.Tensor) -> torch.Tensor:
        if model.last_level:
            g = grad.detach()[0, 0]
            d = self.config.decay
            if self.seen is None:
                self.seen = torch.zeros_like(g)
            self.seen.mul_(d).addcmul_(g, g, value=1 - d)
            self.samples += 1
        return grad

    def after_step(self, model: Model, step: StepRecord) -> None:
        cfg = self.config
        if self.seen is None or self.samples < cfg.after_steps:
            return
        values = model.field.sdf.detach()[0, 0]
        if self.nodes is None or model.level_steps % cfg.refresh_steps == 0:
            self.nodes = unseen_nodes(values, self.seen, cfg.band_voxels * model.field.voxel, cfg.threshold)
            self.relaxed_nodes = int(self.nodes.numel())
        relax_air_side(values, self.nodes, cfg.iterations, cfg.alpha)

    def summary(self) -> dict:
        return {"relaxed_nodes": self.relaxed_nodes}


def unseen_nodes(values: torch.Tensor, seen: torch.Tensor, band_m: float, threshold: float) -> torch.Tensor:
    """Flat indices of the interior nodes of a grid (nz, ny, nx) within band_m (metres) of the surface on its air
    side (0 < value < band_m) whose `seen` (the data gradient's mean square) is below threshold x its mean over the
    nodes within band_m on either side (the regularisers' band). Empty where the band is empty or nothing was
    seen."""
    band = band_nodes(values[None, None], band_m)
    if band.numel() == 0:
        return band
    seen_band = seen.reshape(-1)[band]
    ref = seen_band.mean()
    if not ref > 0:
        return band[:0]
    return band[(values.reshape(-1)[band] > 0) & (seen_band < threshold * ref)]


def relax_air_side(values: torch.Tensor, nodes: torch.Tensor, iterations: int, alpha: float) -> None:
    """In place: `iterations` Jacobi iterations value <- (1 - alpha) value + alpha x (mean of the six neighbours) at
    the interior nodes `nodes` (flat indices) of a grid (nz, ny, nx), each only while its value is positive (a node
    that turns solid is held from then on)."""
    if nodes.numel() == 0:
        return
    nz, ny, nx = values.shape
    flat = values.view(-1)
    offsets = torch.tensor([1, -1, nx, -nx, nx * ny, -nx * ny], device=values.device)
    around = nodes[:, None] + offsets
    with torch.no_grad():
        for _ in range(iterations):
            current = flat[nodes]
            mean = flat[around].mean(dim=1)
            flat[nodes] = torch.where(current > 0, current + alpha * (mean - current), current)


__all__ = ["UnseenConfig", "UnseenRelaxation", "unseen_nodes", "relax_air_side"]
