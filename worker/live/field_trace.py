"""Rays through a snapshot's SDF grid, for view ranking: first surface hits by sphere tracing, and whether a
segment is free of surface. Torch on the CPU (one grid_sample per step for every ray at once); metres throughout.

Outside the grid's box a point reads its distance to the box (empty, as `snapshot.GridSnapshot.sample` says), so a
ray from a sensor half a metre away reaches the box in one step. Inside, a step is the SDF value (never less than
MIN_STEP_VOXELS, never more than MAX_STEP_VOXELS: the grid is a true distance only near the surface), and a hit is
placed between the last two samples by linear interpolation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .snapshot import GridSnapshot

MIN_STEP_VOXELS = 0.5
MAX_STEP_VOXELS = 3.0
TRACE_STEPS = 96
"""Sphere-tracing iterations: enough to cross a 64-voxel box at the smallest useful step from outside it."""


@dataclass
class Hits:
    """First hits of rays (N,): hit (bool), t (metres along the ray; the far limit where there is no hit), point (N, 3),
    normal (N, 3) unit outward (zero where no hit)."""

    hit: torch.Tensor
    t: torch.Tensor
    point: torch.Tensor
    normal: torch.Tensor


class TracedField:
    """A GridSnapshot as a torch volume that points and rays can be traced through."""

    def __init__(self, grid: GridSnapshot):
        self.sdf = torch.as_tensor(np.asarray(grid.sdf, np.float32))[None, None]  # (1, 1, nz, ny, nx)
        self.origin = torch.as_tensor(np.asarray(grid.origin, np.float64), dtype=torch.float32)
        self.voxel = float(grid.voxel_m)
        n = torch.tensor(grid.sdf.shape[::-1], dtype=torch.float32)  # (nx, ny, nz)
        self.size = (n - 1) * self.voxel
        self.hi = self.origin + self.size

    def sample(self, points: torch.Tensor) -> torch.Tensor:
        """SDF (N,) at world points (N, 3); outside the box: the nearest node's value (at least 0) plus the distance
        to the box."""
        inside = torch.minimum(torch.maximum(points, self.origin), self.hi)
        excess = torch.linalg.vector_norm(points - inside, dim=-1)
        g = (inside - self.origin) / self.size * 2 - 1
        v = F.grid_sample(self.sdf, g.reshape(1, 1, 1, -1, 3), mode="bilinear", align_corners=True)
        v = v.reshape(-1)
        return torch.where(excess > 0, v.clamp(min=0) + excess, v)

    def normal(self, points: torch.Tensor) -> torch.Tensor:
        """Unit gradients (N, 3) of the SDF at points (N, 3), by central differences half a voxel wide."""
        h = 0.5 * self.voxel
        grad = torch.stack([self.sample(points + h * e) - self.sample(points - h * e)
                            for e in torch.eye(3, dtype=points.dtype)], dim=-1)
        return grad / grad.norm(dim=-1, keepdim=True).clamp(min=1e-12)

    def trace(self, origins: torch.Tensor, dirs: torch.Tensor, t_max: float | torch.Tensor) -> Hits:
        """First surface hits of rays origins + t dirs (N, 3) with 0 < t < t_max."""
        t_max = torch.as_tensor(t_max, dtype=torch.float32).expand(len(origins))
        t = torch.zeros(len(origins))
        prev_t, prev_v = t.clone(), self.sample(origins)
        hit = torch.zeros(len(origins), dtype=torch.bool)
        alive = prev_v > 0
        lo, hi = MIN_STEP_VOXELS * self.voxel, MAX_STEP_VOXELS * self.voxel
        for _ in range(TRACE_STEPS):
            if not bool(alive.any()):
                break
            idx = torch.nonzero(alive)[:, 0]
            v = prev_v[idx]
            out = self._box_distance(origins[idx] + t[idx, None] * dirs[idx])  # outside the box: straight to it
            step = torch.where(out > 0, out.clamp(min=lo), v.clamp(lo, hi))
            t_new = t[idx] + step
            v_new = self.sample(origins[idx] + t_new[:, None] * dirs[idx])
            crossed = v_new <= 0
            # the crossing, between the last two samples
            frac = v / (v - v_new).clamp(min=1e-12)
            t_hit = t[idx] + frac * step
            done = crossed & (t_hit < t_max[idx])
            hit[idx[done]] = True
            t[idx] = torch.where(crossed, t_hit, t_new)
            prev_v[idx] = v_new
            alive[idx[crossed | (t_new >= t_max[idx])]] = False
        t = torch.where(hit, t, t_max)
        point = origins + t[:, None] * dirs
        normal = torch.zeros_like(point)
        if bool(hit.any()):
            normal[hit] = self.normal(point[hit])
        return Hits(hit, t, point, normal)

    def _box_distance(self, points: torch.Tensor) -> torch.Tensor:
        inside = torch.minimum(torch.maximum(points, self.origin), self.hi)
        return torch.linalg.vector_norm(points - inside, dim=-1)

    def surface(self, floor_z: float | None, max_points: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray,
                                                                                         np.ndarray]:
        """Points on the zero level (marching cubes), above floor_z by a voxel: (points (M, 3), outward normals
        (M, 3), areas (M,) m^2), at most max_points of them (drawn by area; the areas then shared out evenly)."""
        from skimage.measure import marching_cubes

        sdf = self.sdf[0, 0].numpy()
        if not (sdf.min() < 0 < sdf.max()):
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
        verts, faces, _, _ = marching_cubes(sdf, 0.0, spacing=(self.voxel,) * 3)
        verts = verts[:, ::-1] + self.origin.numpy()  # (z, y, x) -> world (x, y, z)
        tri = verts[faces]
        centre = tri.mean(axis=1)
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = 0.5 * np.linalg.norm(cross, axis=1)
        keep = area > 0
        if floor_z is not None:
            keep &= centre[:, 2] > floor_z + self.voxel
        centre, area = centre[keep], area[keep]
        if len(centre) > max_points:
            pick = np.random.default_rng(seed).choice(len(centre), max_points, replace=False, p=area / area.sum())
            centre, area = centre[pick], np.full(max_points, area.sum() / max_points)
        normal = self.normal(torch.as_tensor(centre, dtype=torch.float32)).numpy()
        return centre, normal, area


__all__ = ["TracedField", "Hits"]
