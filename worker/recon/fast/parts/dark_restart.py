"""A dark object's fit started again: from the hull, its albedo read from the counts.

A fit starts its albedo at 1 and learns it at `schedule.albedo_lr`. Every fit's albedo falls in its first steps (the
carved hull is larger than the object and renders too much light); a bright object's turns back up as the grid
carves the hull down to it, a dark object's goes on falling, but the grid answers the excess light faster than the
albedo: the surface shrinks and opens, and the fit settles there, a smaller, holed shape at too high an albedo that
explains the histograms within their noise (a torus of albedo 0.15: 10.6 mm at albedo 0.23, quiet).

A dark object seen from fewer views (a fatter hull) goes wrong another way: its surface collapses to a lump within
the first hundred steps while its albedo, which the lump's excess light no longer pulls, falls slowly from about
0.5 (a 10 cm ball of albedo 0.1 from 64 views: 0.54 at step 200, 15.7 mm at step 800).

At the coarse level's `check_steps`-th step, an albedo below `below`, or below `falling_below` and lower than
`trend_steps` steps before, marks a dark object: the fit starts again from the hull (`FastModel.restart`), its albedo
at the one with which the hull renders as many photons as the views measured (`FastModel.counts_albedo`: the hull's
extra surface makes it read low, 0.4-0.8 of the truth on the dark ones tried, which the fit then learns up from without
carving; the ball: 4.1 mm at step 800). Measured at step 200 on every bright scene of the benchmarks (37 simulated,
two real): 0.57 and more, the one under 0.6 (the plant stand) rising by 0.13 over the 50 steps before; on the dark
objects tried, 0.23-0.37, or 0.46-0.54 and falling. Once per run; not on a warm start (a live fit's rebuilds go on
from the live field, their albedo from 1 again, and are not restarted: a dark object's live fit is not helped), nor
where the coarse level ends before `check_steps` (said in the report's parts left out). Without a signal to read an
albedo from, the restart keeps the albedo the first fit reached.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from spadscan.protocol.errors import ConfigError

from .part import Model, Part, PartConfig, StepRecord


@dataclass
class DarkRestartConfig(PartConfig):
    """When a fit's albedo marks a dark object."""

    check_steps: int = 200
    """Coarse-level step at which the albedo is read (before the refinement, `parts.refinement.after_steps`)."""
    below: float = 0.45
    """An albedo below this at `check_steps` marks a dark object."""
    falling_below: float = 0.6
    """An albedo below this at `check_steps` that is lower than `trend_steps` steps before marks one too."""
    trend_steps: int = 50
    """Steps over which the albedo's fall is read."""

    def check(self, key: str) -> None:
        super().check(key)
        if not (isinstance(self.check_steps, int) and not isinstance(self.check_steps, bool)
                and self.check_steps >= 1):
            raise ConfigError(f"{key}.check_steps {self.check_steps!r} must be an integer >= 1")
        for name in ("below", "falling_below"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                    and 0 < value <= 1):
                raise ConfigError(f"{key}.{name} {value!r} must be in (0, 1] (an albedo; the fit starts at 1)")
        if not (isinstance(self.trend_steps, int) and not isinstance(self.trend_steps, bool)
                and 1 <= self.trend_steps < self.check_steps):
            raise ConfigError(f"{key}.trend_steps {self.trend_steps!r} must be an integer in [1, "
                              f"{key}.check_steps - 1]")


class DarkRestart(Part):
    """Reads the albedo once, at the coarse level's `check_steps`-th step, and restarts a dark object's fit."""

    name = "dark_restart"

    @classmethod
    def left_out(cls, config: DarkRestartConfig, model: Model) -> str | None:
        refine = model.config.parts.refinement
        if refine.enabled and refine.after_steps <= config.check_steps:
            return (f"the albedo is read at the coarse level's step {config.check_steps} "
                    f"(parts.dark_restart.check_steps), and the grid is refined after {refine.after_steps} "
                    f"(parts.refinement.after_steps)")
        return None

    def __init__(self, config: DarkRestartConfig, model: Model):
        super().__init__(config, model)
        self.albedo_before: float | None = None
        self.albedo_at_check: float | None = None
        self.restarted_at_step: int | None = None
        self.counts_albedo: float | None = None

    def after_step(self, model: Model, step: StepRecord) -> None:
        cfg = self.config
        if self.albedo_at_check is not None or model.warm_started or model.level != 0:
            return
        if model.level_steps == cfg.check_steps - cfg.trend_steps:
            self.albedo_before = model.albedo()
        if model.level_steps != cfg.check_steps:
            return
        albedo = self.albedo_at_check = model.albedo()
        falling = self.albedo_before is not None and albedo < self.albedo_before
        if not (albedo < cfg.below or (albedo < cfg.falling_below and falling)):
            return
        model.restart()
        self.counts_albedo = model.counts_albedo()  # read on the hull it starts from
        # Without a signal to read it from, the albedo stays where the first fit took it.
        if self.counts_albedo is not None:
            model.set_albedo(self.counts_albedo)
        self.restarted_at_step = model.steps

    def summary(self) -> dict:
        return {"albedo_before": self.albedo_before, "albedo_at_check": self.albedo_at_check,
                "restarted_at_step": self.restarted_at_step,
                "counts_albedo": self.counts_albedo}


__all__ = ["DarkRestart", "DarkRestartConfig"]
