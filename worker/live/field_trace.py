"""Rays through a snapshot's SDF grid, for view ranking: first surface hits by sphere tracing, and whether a
segment is free of surface. Torch on the CPU (one grid_sample per step for every ray at once); metres throughout.

Only the part of a ray inside the grid's box is traced (outside it, as `snapshot.GridSnapshot.sample` says, all is
empty). A step is the SDF value (never less than MIN_STEP_VOXELS, never more than MAX_STEP_VOXELS: the grid is a true
distance only near the surface), and a hit is placed between the last two samples by linear interpolation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .snapshot import GridSnapshot

MIN_STEP_VOXELS = 0.5
MAX_STEP_VOXELS = 3.0
TRACE_STEPS = 128
"""Sphere-tracing iterations at most: enough to cross a 64-voxel box diagonally at one voxel a step."""


@dataclass
class Hits:
    """First hits of rays (N,): hit (bool), t (metres along the ray; where there is no hit, where the ray leaves the
    grid's box, or the far limit when it never enters it), point (N, 3), normal (N, 3) unit outward (zero where no
    hit)."""

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

    def trace(self, origins: torch.Tensor, dirs: torch.Tensor, t_max: float | torch.Tensor,
              normals: bool = True) -> Hits:
        """First surface hits of rays origins + t dirs (N, 3) (unit dirs) with 0 < t < t_max; the normals at the hits
        unless `normals` is False (then zero). Only the part of each ray inside the grid's box is traced: nothing
        stands outside it."""
        n = len(origins)
        t_in, t_out, t_hit = self._clipped_span(origins, dirs, t_max)  # t_hit: where a ray that hits nothing leaves
        hit = torch.zeros(n, dtype=torch.bool)
        idx = torch.nonzero(t_in < t_out)[:, 0]
        o, d, end = origins[idx], dirs[idx], t_out[idx]
        t = t_in[idx]
        v = self.sample(o + t[:, None] * d)
        keep = v > 0  # a ray that starts inside the surface has no first hit in front of it
        idx, o, d, end, t, v = idx[keep], o[keep], d[keep], end[keep], t[keep], v[keep]
        lo, hi = MIN_STEP_VOXELS * self.voxel, MAX_STEP_VOXELS * self.voxel
        for _ in range(TRACE_STEPS):
            if len(idx) == 0:
                break
            step = v.clamp(lo, hi)
            t_new = t + step
            v_new = self.sample(o + t_new[:, None] * d)
            crossed = v_new <= 0
            at = t + v / (v - v_new).clamp(min=1e-12) * step  # the crossing, between the last two samples
            found = crossed & (at < end)
            hit[idx[found]] = True
            t_hit[idx[found]] = at[found]
            going = ~crossed & (t_new < end)
            idx, o, d, end, t, v = idx[going], o[going], d[going], end[going], t_new[going], v_new[going]
        point = origins + t_hit[:, None] * dirs
        normal = torch.zeros_like(point)
        if normals and bool(hit.any()):
            normal[hit] = self.normal(point[hit])
        return Hits(hit, t_hit, point, normal)

    def box_exit(self, origins: torch.Tensor, dirs: torch.Tensor, t_max: float | torch.Tensor) -> torch.Tensor:
        """(N,) where each ray leaves the box before t_max (t_max where it never enters it): the `t` that `trace`
        gives a ray that hits nothing."""
        return self._clipped_span(origins, dirs, t_max)[2]

    def _clipped_span(self, origins: torch.Tensor, dirs: torch.Tensor, t_max: float | torch.Tensor):
        """(t_in, t_out, exit) (N,): the part of each ray inside the box, cut at t_max, and where the ray leaves it
        (t_max where it never enters)."""
        t_max = torch.as_tensor(t_max, dtype=torch.float32).expand(len(origins))
        t_in, t_out = self._box_span(origins, dirs)
        t_out = torch.minimum(t_out, t_max)
        return t_in, t_out, torch.where(t_in < t_out, t_out, t_max)

    def _box_span(self, origins: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(t_in, t_out) (N,) of each ray's part inside the box, t_in >= 0; t_in >= t_out where it misses."""
        inv = 1.0 / torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
        a, b = (self.origin - origins) * inv, (self.hi - origins) * inv
        t_in = torch.minimum(a, b).amax(dim=-1).clamp(min=0.0)
        t_out = torch.maximum(a, b).amin(dim=-1)
        return t_in, t_out

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
