"""Does the mesh reach down to the floor its object stands on? Views aimed high on a tall object (a head on a
square plinth, 35 cm tall, its 256 views aimed at its mid-height from 0.5 m) never look at its foot: the low views'
fields end above it and the views from above have the head in front of it. The fit leaves the foot out, and no other
check sees that (no histogram holds a return of what no view looked at; the coverage counts only the surface the
mesh has): the head came out 6.33 mm, its mesh stopping 4.7 cm above the floor, the plinth gone.

The object stands on the fit's floor (`field.floor_z`, z = 0 where simulated scenes stand, or the capture's
`scene.floor_z`), so its mesh reaches down to it; a mesh whose lowest point stands over GAP_LIMIT_M above it has
lost its foot, or its object does not stand on that floor. Not on a table, whose fitted height is another matter
(the real pyramid's mesh reaches below its table's top).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GAP_LIMIT_M = 0.03
"""Gap (metres) between the mesh's lowest point and the floor over which the result says so: the head on a plinth
aimed at its mid-height 0.047; every benchmark fit without a table at most 0.015 (the same head fitted in the grid
round its whole hull; a ball touching the floor at one point 0.013), aimed at the floor at most 0.008."""
FLOOR_SOURCES = {"config": "field.floor_z", "capture": "the capture's scene.floor_z"}
"""The floors that are judged, by the fast preset's `floor` note, and what sets each: a table is not judged."""


@dataclass
class FloorGap:
    """How far above its floor the mesh stops."""

    floor_z: float
    """The floor's height (world z, metres)."""
    bottom_z: float
    """The mesh's lowest point (world z, metres)."""
    source: str
    """What set the floor: a key of FLOOR_SOURCES."""

    @property
    def gap_m(self) -> float:
        return self.bottom_z - self.floor_z

    def to_dict(self) -> dict:
        return {"floor_z_m": self.floor_z, "bottom_z_m": self.bottom_z, "gap_m": self.gap_m, "floor": self.source,
                "limit_m": GAP_LIMIT_M}


def floor_gap(vertices: np.ndarray, floor_z, source) -> FloorGap | None:
    """The gap between a mesh (`vertices` (n, 3), world metres) and the floor at `floor_z` (metres) that `source`
    (the fast preset's `floor` note) set; None for a mesh without vertices, no floor, or a floor that is a table."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    if not len(vertices) or source not in FLOOR_SOURCES or not isinstance(floor_z, (int, float)) \
            or isinstance(floor_z, bool) or not np.isfinite(floor_z):
        return None
    return FloorGap(floor_z=float(floor_z), bottom_z=float(vertices[:, 2].min()), source=source)


def gap_warning(gap: FloorGap | None) -> str | None:
    """The line saying that the mesh stops well above the floor its object stands on, or None."""
    if gap is None or not gap.gap_m > GAP_LIMIT_M:
        return None
    return (f"the mesh stops {100 * gap.gap_m:.1f} cm above the floor it stands on (z = {gap.floor_z:.3f} m, "
            f"{FLOOR_SOURCES[gap.source]}): the object's foot may be missing, where no view looked (views aimed high "
            f"on a tall object: a head on a plinth aimed at its mid-height lost the plinth, 6.3 mm), or the object "
            f"does not stand on that floor; aim the views lower (the schedule's target at the floor under the "
            f"object) or set the floor's height")


__all__ = ["FloorGap", "floor_gap", "gap_warning", "GAP_LIMIT_M", "FLOOR_SOURCES"]
