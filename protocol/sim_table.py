"""A table for the simulator: the horizontal top of a square slab under the object, with its own albedo.

Real captures see the table in every histogram (the object stands on it, and every zone that misses the object lands
on it); LCSPCData's simulated scenes render none. The table is a plane z = height_m cut to a square of half-size
half_size_m about the z axis, opaque from both sides, Lambertian with `albedo` (relative to the sensor model's
signal scale, like the object's). Rays are met analytically: exact, and no large triangles for the ray caster.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import SimulationError

DEFAULT_ALBEDO = 0.1
"""A black table under a white object (albedo 1): a tenth of its return, the hard case of a faint table. Relative to
the tmf8820 preset, LCSPCData's real table returns about 1.35x what its real pyramid does (both fitted with the
sensor's signal scale; in the outer zones, where the table shows beside the pyramid): to mimic that scene, simulate
the object at albedo 1 on a table of 1.35."""
DEFAULT_HALF_SIZE_M = 1.0
"""Half the side of the table's square (metres): a 2 m table, wider than any view of a scan reaches."""
CUT_TOLERANCE_M = 0.003
"""How far (metres) the table top may lie above the object's lowest point: a mesh's feet may dip a hair below the
plane it was modelled on. More, and the table cuts the object (or, above all of it, hangs over it)."""
FLOAT_WARN_M = 0.01
"""A gap (metres) between the table top and the object's lowest point beyond which the object floats: wider than a
mesh's rounding, and close to a tmf8820 bin (13.6 mm), where the table shows as a return of its own under the
object."""

TOP_TOLERANCE_M = 1e-6
"""A sensor closer than this (metres) above the table top counts as standing on it: where a schedule puts a ring at
the table's height, rounding leaves it a hair above or below."""


@dataclass(frozen=True)
class SimTable:
    """A horizontal table top at height_m (metres), albedo relative to the sensor's signal scale, a square of
    half-size half_size_m (metres) centred on the z axis."""

    height_m: float = 0.0
    albedo: float = DEFAULT_ALBEDO
    half_size_m: float = DEFAULT_HALF_SIZE_M

    def check(self) -> "SimTable":
        for key, lo, hi in (("height_m", -100.0, 100.0), ("albedo", 0.0, 1e3), ("half_size_m", 1e-6, 1e3)):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and lo <= v <= hi):
                raise SimulationError(f"table {key} = {v!r} is outside [{lo:g}, {hi:g}]")
        return self

    def gap_below(self, lowest_z: float) -> float:
        """Metres from the table top up to an object's lowest point (z, metres): negative when the table lies above
        it (see CUT_TOLERANCE_M, FLOAT_WARN_M)."""
        return float(lowest_z) - self.height_m

    def hits(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(range (N,) metres along each ray to the table, inf where the ray never meets it; |cos| of incidence
        (N,)) for rays origins, directions (N, 3) (directions unit). A ray that starts on the top and heads down into
        the slab meets it at range 0 (one heading up leaves it): no sensor can stand there, and the table must not
        vanish from its histograms as if it were not there."""
        dz = directions[:, 2]
        moving = np.abs(dz) > 1e-12
        t = np.where(moving, (self.height_m - origins[:, 2]) / np.where(moving, dz, 1.0), np.inf)
        t = np.where((t > 0) | ((t == 0) & (dz < 0)), t, np.inf)
        finite = np.isfinite(t)
        x = origins[:, 0] + np.where(finite, t, 0.0) * directions[:, 0]
        y = origins[:, 1] + np.where(finite, t, 0.0) * directions[:, 1]
        inside = (np.abs(x) <= self.half_size_m) & (np.abs(y) <= self.half_size_m)
        return np.where(finite & inside, t, np.inf), np.abs(dz)

    def below_top(self, points: np.ndarray) -> np.ndarray:
        """Which points (N, 3) (metres) lie on the table top or under it (within its square, TOP_TOLERANCE_M): no
        sensor can stand there."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        over = (np.abs(p[:, 0]) <= self.half_size_m) & (np.abs(p[:, 1]) <= self.half_size_m)
        return over & (p[:, 2] <= self.height_m + TOP_TOLERANCE_M)

    def record(self) -> dict:
        """What a capture's scene record keeps of the table (metres)."""
        return {"z": float(self.height_m), "albedo": float(self.albedo), "half_size_m": float(self.half_size_m)}


__all__ = ["SimTable", "DEFAULT_ALBEDO", "DEFAULT_HALF_SIZE_M", "CUT_TOLERANCE_M", "FLOAT_WARN_M", "TOP_TOLERANCE_M"]
