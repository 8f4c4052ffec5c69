"""Does the mesh's top lie within the views' fields? Views aimed too low at a tall object (a schedule's target at the
floor under a 25 cm teddy, its views up to 45 degrees) never see its top: carving's hull ends where the views'
fields end, and the fit's mesh is cut flat there, a part of the object gone that no other check sees (the fit
explains every histogram, since none saw the part; the coverage counts only the surface the mesh has, and its cut
top is a small share of it). The teddy came out 6.43 mm, its top 7 cm low, with nothing said.

The check takes the mesh's vertices within TOP_BAND_M of its highest point and asks of the point LIFT_M above each
whether it lies in the field of any zone of any view that holds data (facing and occlusion aside: a point outside
every field is unseen whatever stands around it). Where the object ends, a view saw the space above it empty (the
view from above sees it whole); where the views stopped, the mesh's top lies at the edge of their fields, and
nothing above it was looked at.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spadscan.protocol.sensor_model import SensorModel

from .coverage import in_usable_zones

TOP_BAND_M = 0.01
"""How far below the mesh's highest point (metres) its vertices count as its top."""
LIFT_M = 0.02
"""How far above each top vertex (metres) the space is looked at: where the object ends, a view saw it empty."""
UNSEEN_TOP_SHARE = 0.5
"""Share of the top's vertices with no view's field LIFT_M above them over which the result says so: the teddy seen
up to 45 degrees 0.97 (35 degrees: 1.00, 25: 0.79); the benchmark's fits and ground truths 0.15 at most."""
MIN_TOP_WIDTH_M = 0.03
"""Narrowest top (the largest horizontal extent of its vertices, metres) that is judged: a cut top is as wide as the
object there (the teddy's 12-13 cm), whereas a pointed one, the real pyramid's apex (2 cm across in its mesh), can
stand just under the reach of views that close in on it (its ground truth's apex: nothing 2 cm above it in any
field), and the part cut off a point is small."""


@dataclass
class TopReach:
    """How much of the mesh's top lies outside every view's field."""

    top_z: float
    """The mesh's highest point (world z, metres)."""
    vertices: int
    """Its vertices within TOP_BAND_M of that height."""
    unseen: int
    """Of them, those with no zone's field of any view with data LIFT_M above them."""
    width_m: float = 0.0
    """The largest horizontal extent of the top's vertices (metres)."""

    @property
    def share(self) -> float:
        return self.unseen / self.vertices if self.vertices else 0.0

    def to_dict(self) -> dict:
        return {"top_z_m": self.top_z, "vertices": self.vertices, "unseen": self.unseen, "share": self.share,
                "width_m": self.width_m, "limit": UNSEEN_TOP_SHARE}


def top_reach(vertices: np.ndarray, poses: np.ndarray, sensor: SensorModel,
              usable: np.ndarray | None = None) -> TopReach | None:
    """The top of a mesh (`vertices` (n, 3), world metres) against the fields of the views `poses` (V, 4, 4, sensor
    to world); `usable` (V, Z) bool, None for all: a zone without data saw nothing. None for a mesh without vertices
    or a capture without a view with data."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    poses = np.asarray(poses, np.float64)
    if not len(vertices) or not len(poses):
        return None
    usable = np.ones((len(poses), len(sensor.zones)), bool) if usable is None else \
        np.asarray(usable, bool).reshape(len(poses), -1)
    if not usable.any():
        return None
    top_z = float(vertices[:, 2].max())
    band = vertices[vertices[:, 2] >= top_z - TOP_BAND_M]
    top = band + np.array([0.0, 0.0, LIFT_M])
    seen = np.zeros(len(top), bool)
    for pose, held in zip(poses, usable):
        if not held.any():
            continue
        rel = (top[~seen] - pose[:3, 3]) @ pose[:3, :3]  # sensor frame
        seen[np.flatnonzero(~seen)[in_usable_zones(sensor, rel, held)]] = True
        if seen.all():
            break
    return TopReach(top_z=top_z, vertices=len(top), unseen=int((~seen).sum()),
                    width_m=float(np.ptp(band[:, :2], axis=0).max()))


def top_warning(reach: TopReach | None) -> str | None:
    """The line saying that no view looked just above most of a wide top of the mesh, or None."""
    if reach is None or not reach.share > UNSEEN_TOP_SHARE or not reach.width_m >= MIN_TOP_WIDTH_M:
        return None
    return (f"no view looked above the mesh's top, at {reach.top_z:.2f} m ({100 * reach.share:.0f} % of it has no "
            f"view's field {100 * LIFT_M:.0f} cm above it): the object may stand taller and the mesh be cut where the "
            f"views stopped (a 25 cm teddy seen by views up to 45 degrees about its base: its top 7 cm low, 6.4 mm); "
            f"aim the views higher (the schedule's target at the object's mid-height) or add views from above")


__all__ = ["TopReach", "top_reach", "top_warning", "TOP_BAND_M", "LIFT_M", "UNSEEN_TOP_SHARE", "MIN_TOP_WIDTH_M"]
