"""When a fit has stopped improving: a plateau test on a noisy per-step loss.

Each step renders a few random views, so the per-step data term scatters by a few percent; its mean over a window of
steps is steady enough to compare. The test keeps the best window mean so far and reports a plateau once no window
has beaten it by a relative margin for `patience` steps (what that buys on the dataset's scenes:
`FastScheduleConfig.patience_steps`). The data term is not the geometric error: on a real scene, where the sensor
model is imperfect, the data term can keep improving while the Chamfer grows.
"""

from __future__ import annotations

import math

from spadscan.protocol.errors import ConfigError


class Plateau:
    """Feed one loss per step to `update`; it returns True from the step the loss has plateaued on."""

    def __init__(self, patience: int, min_rel_improvement: float, window: int | None = None):
        if patience < 1 or not math.isfinite(min_rel_improvement) or min_rel_improvement < 0:
            raise ConfigError(f"plateau test needs schedule.patience_steps >= 1 and a finite "
                              f"schedule.min_rel_improvement >= 0, got {patience} and {min_rel_improvement}")
        self.patience, self.min_rel = int(patience), float(min_rel_improvement)
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


__all__ = ["Plateau"]
