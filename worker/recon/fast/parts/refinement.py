"""Coarse to fine: the grid is refined 2x once, after `after_steps` steps on the coarse level.

A coarse step is cheap and moves the surface far, so the coarse level finds the shape; the fine level then places
the surface to a fraction of its (halved) voxel. The refinement keeps the field (`GridField.upsampled` interpolates
the old nodes trilinearly, so the zero level set is unchanged) and restarts the level: the step counter of the level,
the optimiser's moments and every part's state that follows the grid (`Part.on_refine`). Switched off, the coarse
grid is the only level: its learning rate decays and its convergence is tested from the start.
"""

from __future__ import annotations

from dataclasses import dataclass

from spadscan.protocol.errors import ConfigError

from .part import Model, Part, PartConfig


@dataclass
class RefinementConfig(PartConfig):
    """When the grid is refined."""

    after_steps: int = 300
    """Steps at the coarse level before the grid is refined 2x."""

    def check(self, key: str) -> None:
        super().check(key)
        if not (isinstance(self.after_steps, int) and self.after_steps >= 1):
            raise ConfigError(f"{key}.after_steps {self.after_steps!r} must be an integer >= 1 ({key}.enabled=false: "
                              f"never refine)")


class Refinement(Part):
    """Refines the grid at the start of the step that follows the coarse level's last."""

    name = "refinement"

    def __init__(self, config: RefinementConfig, model: Model):
        super().__init__(config, model)
        self.refined_at_step: int | None = None

    def before_step(self, model: Model) -> None:
        if model.level == 0 and model.level_steps >= self.config.after_steps:
            self.refined_at_step = model.steps
            model.refine()

    def summary(self) -> dict:
        return {"refined_at_step": self.refined_at_step}


__all__ = ["Refinement", "RefinementConfig"]
