"""When a fit has stopped improving: a plateau test on a noisy per-step loss.

Each step renders a few random views, so the per-step data term scatters by a few percent; its mean over a window of
steps is steady enough to compare. The test keeps the best window mean so far and reports a plateau once no window
has beaten it by a relative margin for `patience` steps. The data term is not the geometric error: on a real scene,
where the sensor model is imperfect, the data term can keep improving while the Chamfer grows.

The part tests the last level only (the test starts afresh at refinement): the run reports `converged` (and, with
the run setting `early_stop`, ends) once its data term has plateaued there. Measured on LCSPCData's simulated scenes
(step-based runs): the bunny stops near 2,400 steps with the Chamfer it ends a 3,000-step run with; the soap near
2,250 steps at 1.9 mm, where a 4,500-step run drifts to 2.2 mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from spadscan.protocol.errors import ConfigError

from .part import Model, Part, PartConfig, StepRecord


@dataclass
class PlateauConfig(PartConfig):
    """How long and by how much the data term must stop improving."""

    patience_steps: int = 600
    """Steps without a window mean (windows of max(10, patience / 6) steps) that beat the best by
    `min_rel_improvement`."""
    min_rel_improvement: float = 0.001
    """Relative improvement of the windowed data term that counts as progress."""

    def check(self, key: str) -> None:
        super().check(key)
        if not (isinstance(self.patience_steps, int) and self.patience_steps >= 1):
            raise ConfigError(f"{key}.patience_steps {self.patience_steps!r} must be an integer >= 1")
        if not (math.isfinite(self.min_rel_improvement) and self.min_rel_improvement >= 0):
            raise ConfigError(f"{key}.min_rel_improvement {self.min_rel_improvement} must be finite and >= 0")


class Plateau:
    """Feed one loss per step to `update`; it returns True from the step the loss has plateaued on."""

    def __init__(self, patience: int, min_rel_improvement: float, window: int | None = None):
        if patience < 1 or not math.isfinite(min_rel_improvement) or min_rel_improvement < 0:
            raise ConfigError(f"plateau test needs parts.plateau.patience_steps >= 1 and a finite "
                              f"parts.plateau.min_rel_improvement >= 0, got {patience} and {min_rel_improvement}")
        self.patience, self.min_rel = int(patience), float(min_rel_improvement)
        # At least 10 steps, so that a window averages out the per-step scatter (each step renders a few random
        # views) even for the small patience a short run is given.
        self.window = int(window) if window else max(10, self.patience // 6)
        self.best = math.inf
        self.since_best = 0
        self.reached = False
        self._sum, self._n = 0.0, 0

    def update(self, loss: float) -> bool:
        """Count one step's loss; True once `patience` steps have passed without a window mean that beat the best by
        `min_rel_improvement` (relative). Non-finite losses count as no improvement."""
        self._sum += loss if math.isfinite(loss) else math.inf
        self._n += 1
        if self._n < self.window:
            return self.reached
        mean = self._sum / self._n
        self._sum, self._n = 0.0, 0
        # The first finite window is the first best (inf - x * inf would be nan, and nothing compares below nan).
        if math.isfinite(mean) and (math.isinf(self.best) or mean < self.best - self.min_rel * abs(self.best)):
            self.best, self.since_best = mean, 0
        else:
            self.since_best += self.window
        self.reached = self.reached or self.since_best >= self.patience
        return self.reached


class PlateauPart(Part):
    """Feeds each step's data term to a `Plateau`, afresh on every level; `converged` once the last level's has
    plateaued."""

    name = "plateau"

    def __init__(self, config: PlateauConfig, model: Model):
        super().__init__(config, model)
        self.plateau = Plateau(config.patience_steps, config.min_rel_improvement)

    def converged(self, model: Model) -> bool:
        return model.last_level and self.plateau.reached

    def after_step(self, model: Model, step: StepRecord) -> None:
        self.plateau.update(float(step.data.detach()))

    def on_refine(self, model: Model) -> None:
        self.plateau = Plateau(self.config.patience_steps, self.config.min_rel_improvement)


__all__ = ["Plateau", "PlateauPart", "PlateauConfig"]
