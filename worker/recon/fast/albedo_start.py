"""The object's albedo a fit starts from, read from the photon counts before its first step.

A fit's albedo starts at 1 and learns at `schedule.albedo_lr` while the grid moves at its full rate. On a dark object
the first steps render several times the signal the sensor saw, and the grid answers faster than the albedo: the
surface shrinks and opens, and the fit settles there (a torus of albedo 0.15: the albedo came to 0.23 and the shape
to 10.6 mm, a smaller holed surface that explains the histograms within their noise). The counts say how dark the
object is before any step: the albedo at which the starting field's expected counts total the counts measured. The
hull is larger than the object, so the estimate reads somewhat low; it is a start, which the fit goes on to learn.
"""

from __future__ import annotations

import math
from typing import Callable

ALBEDO_LO, ALBEDO_HI = 1e-3, 1e3
"""The albedos the estimate is sought between (the bounds themselves where the counts lie beyond them)."""

BISECTIONS = 40
"""Halvings of the log-albedo interval: 40 bring it from 14 to 1e-11 (the estimate's own error is far larger)."""


def albedo_for_total(total_at: Callable[[float], float], measured: float) -> float | None:
    """The albedo a with total_at(a) = measured, by bisection in log a over [ALBEDO_LO, ALBEDO_HI]. total_at: the
    expected counts (photons) the views would hold at albedo a, non-decreasing in a; measured: the counts they hold.
    None where the counts hold no more than the background (total_at at the lowest albedo), or they or the model's
    totals are not finite: nothing to read an albedo from. ALBEDO_HI where even it falls short."""
    least, most = total_at(ALBEDO_LO), total_at(ALBEDO_HI)
    if not all(math.isfinite(x) for x in (measured, least, most)) or measured <= least:
        return None
    if most <= measured:
        return ALBEDO_HI
    lo, hi = math.log(ALBEDO_LO), math.log(ALBEDO_HI)
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        total = total_at(math.exp(mid))
        if not math.isfinite(total):  # a model that renders nothing sound: no albedo to read
            return None
        if total < measured:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


__all__ = ["ALBEDO_HI", "ALBEDO_LO", "albedo_for_total"]
