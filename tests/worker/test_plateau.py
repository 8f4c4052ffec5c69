"""The plateau test behind the fast preset's `converged` flag and early stop."""

import math

import numpy as np
import pytest

from spadscan.protocol.errors import ConfigError
from spadscan.worker.recon.fast.parts.plateau import Plateau


def first_reached(plateau: Plateau, losses) -> int | None:
    for i, loss in enumerate(losses, start=1):
        if plateau.update(float(loss)):
            return i
    return None


def test_a_flat_loss_plateaus_one_patience_after_its_first_window():
    # The first window is the first best: the plateau is reached `patience` steps after it, not after `patience`
    # steps in all (comparing with an infinite best once made every run 'converge' at the earliest possible step).
    assert first_reached(Plateau(patience=60, min_rel_improvement=1e-3, window=10), [1.0] * 200) == 70


def test_a_loss_that_keeps_improving_never_plateaus():
    losses = 1.0 * 0.998 ** np.arange(3000)  # 2% per 10-step window, far above the 0.1% margin
    assert first_reached(Plateau(patience=60, min_rel_improvement=1e-3, window=10), losses) is None


def test_noise_around_a_floor_plateaus_and_a_new_drop_postpones_it():
    rng = np.random.default_rng(0)
    noisy = 0.5 + 0.02 * rng.standard_normal(400)  # per-step scatter; window means scatter ~0.6%
    slow = Plateau(patience=120, min_rel_improvement=0.05, window=20)
    reached = first_reached(slow, noisy)
    assert reached is not None and 140 <= reached <= 400
    # The same floor, but a drop by a third at step 100: the best moves and the count starts again.
    dropped = np.concatenate([noisy[:100], noisy[100:] * 0.66])
    later = first_reached(Plateau(patience=120, min_rel_improvement=0.05, window=20), dropped)
    assert later is not None and later >= 100 + 120


def test_non_finite_losses_count_as_no_improvement():
    p = Plateau(patience=20, min_rel_improvement=1e-3, window=10)
    assert first_reached(p, [1.0] * 10 + [math.nan] * 10 + [math.inf] * 10) == 30
    assert p.best == 1.0


@pytest.mark.parametrize("patience, rel", [(0, 1e-3), (10, -0.1), (10, math.nan)])
def test_bad_settings_are_refused(patience, rel):
    with pytest.raises(ConfigError, match="plateau"):
        Plateau(patience=patience, min_rel_improvement=rel)
