"""What the live job hands to whoever ranks the next views: plain numpy arrays, no torch tensors, no model.

A `LiveSnapshot` is taken every few seconds while a scan runs. It holds the last few SDF grids the live model went
through (oldest first: their disagreement says where the shape is still moving), the space-carving hull of the views
used so far (what no view has proven empty), the sensor poses of those views and the capture's sensor model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spadscan.protocol.sensor_model import SensorModel


@dataclass(frozen=True)
class GridSnapshot:
    """A signed-distance grid in world metres, negative inside.

    Node (i, j, k) sits at `origin + voxel_m * (i, j, k)` (x, y, z); `sdf` is stored (nz, ny, nx), float32."""

    sdf: np.ndarray
    origin: np.ndarray
    """(3,) world position of node (0, 0, 0), metres."""
    voxel_m: float

    def sample(self, points: np.ndarray) -> np.ndarray:
        """Trilinear SDF at world points (..., 3) metres -> (...); points outside the box read the nearest node
        value plus their distance to the box (empty)."""
        pts = np.asarray(points, float)
        shape = pts.shape[:-1]
        p = pts.reshape(-1, 3)
        n = np.array(self.sdf.shape[::-1])  # (nx, ny, nz)
        u = (p - self.origin) / self.voxel_m
        inside = np.clip(u, 0, n - 1)
        excess = np.linalg.norm(u - inside, axis=1) * self.voxel_m
        i0 = np.minimum(np.floor(inside).astype(np.int64), n - 2)
        f = inside - i0
        out = np.zeros(len(p))
        for dz in (0, 1):
            for dy in (0, 1):
                for dx in (0, 1):
                    w = ((f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1])
                         * (f[:, 2] if dz else 1 - f[:, 2]))
                    out += w * self.sdf[i0[:, 2] + dz, i0[:, 1] + dy, i0[:, 0] + dx]
        out = np.where(excess > 0, np.maximum(out, 0.0) + excess, out)
        return out.reshape(shape)


@dataclass(frozen=True)
class FieldSnapshot:
    """The live model's field at one moment."""

    grid: GridSnapshot
    step: int
    """Optimisation steps the live model had taken."""
    views_used: int
    """Views the model was fitting at that moment."""


@dataclass(frozen=True)
class LiveSnapshot:
    """The state of a live reconstruction, for ranking candidate views (`next_views.rank_candidates`)."""

    fields: list[FieldSnapshot]
    """The last few field snapshots, oldest first (at least one)."""
    hull: GridSnapshot
    """Signed distance of the carved hull of the views used so far (negative where no view proved space empty)."""
    poses: np.ndarray
    """(V, 4, 4) sensor-to-world poses of the views taken, metres: those the model fits, or every view published
    (`next_views.update_next_views`)."""
    sensor: SensorModel
    """The capture's sensor model (zones, bins, range)."""
    floor_z: float | None = None
    """Nothing is solid below this height (metres), or None."""
    converged: bool = False
    """The live model reports convergence on the views it has."""
    notes: dict = field(default_factory=dict)
    """Anything else worth passing on (JSON-able)."""

    @property
    def latest(self) -> FieldSnapshot:
        return self.fields[-1]


__all__ = ["GridSnapshot", "FieldSnapshot", "LiveSnapshot"]
