"""When a live fit's rebuild goes back to the coarse level (torch-free: the live job's settings hold it).

A scan visits its poses along a short path, so its first views see the object from one side: a coarse level spent on
them finds a shape that later views contradict, and the fine level, which places the surface to a fraction of its
voxel, does not move it far. Re-entering the coarse level (warm, from the live surface) each time the views have grown
by half lets the coarse shape follow the scan. Measured by `benchmarks/live_recoarse.py`.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RecoarsePolicy:
    """When a rebuild re-enters the coarse level instead of going on at the live model's level."""

    growth: float = 1.5
    """Once the views number this many times those the coarse level last began with (0: never re-enter it) ..."""
    until: float = 0.5
    """... and only while the views are under this share of the planned ones: later, the scan's end would find the
    fit back on the coarse level with too little time left for the fine one (under 3/4: 404 fine steps on the
    complete capture at the end of the step-based study; under 1/2: 884, and 0.12 mm better on both tuning
    scenes, the cup and the goblet)."""

    def due(self, coarse_views: int, views: int, planned: int | None) -> bool:
        if self.growth <= 0 or views < self.growth * coarse_views:
            return False
        return planned is None or views < self.until * planned


__all__ = ["RecoarsePolicy"]
