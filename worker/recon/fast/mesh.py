"""Meshes from SDF grids: marching cubes at the zero level, in world metres."""

from __future__ import annotations

import numpy as np
import torch
import trimesh
from scipy import ndimage
from skimage.measure import marching_cubes

from ..errors import ReconstructionError
from .grid_ops import below_floor, cavities, fill_under_overhangs, node_heights, open_nodes

FLOATER_FRACTION = 0.02
"""On a table, solid pieces of a mesh's grid smaller than this fraction of the largest piece (by node count) are
floaters. On LCSPCData's real pyramid the fits leave one to three such pieces on the table, 0.5-0.7% of the object's
volume, 1-2 cm outside its base (a wall up to 6 cm tall); removing them lowered the Chamfer by 0.05-0.24 mm in four
fits (the previous cut, 0.5%, kept them). Without a table nothing is removed: there a fit's small pieces are mostly
the object's own thin parts broken off, and removing them cost up to 1.5 mm (a plant stand's legs: 3.87 mm removed,
2.37 kept; the stool 3.95 against 3.04) where it bought at most 0.05 mm (specks beside the demo goblet), step-based
on every scene without a table (benchmarks/RESULTS.md, "Small pieces kept")."""


def clean_solid(values: np.ndarray, min_fraction: float = 0.0,
                below_floor: np.ndarray | None = None, fill_pockets: bool = True) -> np.ndarray:
    """Remove what the histograms cannot have seen from an SDF grid (nz, ny, nx) -> cleaned copy.

    Cavities (`cavities`: empty regions closed by the solid, and by the floor when `below_floor` marks it) lie behind
    every surface a sensor outside can see: they are filled (unless not `fill_pockets`). Solid pieces smaller than
    `min_fraction` of the largest piece (by node count) are floaters: they are emptied (0, the default: none is).
    Filled and emptied nodes get a value of half a node spacing's worth (+-1e-3 of the field's scale), so the surface
    moves only where something was removed.
    """
    v = np.array(values, np.float32, copy=True)
    solid = v < 0
    if not solid.any():
        return v
    eps = 1e-4 * max(float(np.abs(v).max()), 1e-6)
    if fill_pockets:
        v[cavities(solid, below_floor)] = -eps
    if min_fraction > 0:
        lab, n = ndimage.label(v < 0)
        if n > 1:
            sizes = np.bincount(lab.ravel())[1:]
            small = np.flatnonzero(sizes < min_fraction * sizes.max()) + 1
            v[np.isin(lab, small)] = eps
    return v


def mesh_from_values(values: np.ndarray, origin, spacing):
    """Marching cubes of an SDF grid (nz, ny, nx) with nodes at origin + spacing * (x, y, z) -> trimesh.Trimesh.

    spacing: a voxel size or (3,) sizes along x, y, z (metres). Raises ReconstructionError when the grid holds no
    surface (all inside or all outside) or is not finite.
    """
    v = np.asarray(values, np.float32)
    if v.ndim != 3 or not np.all(np.isfinite(v)):
        raise ReconstructionError(f"the SDF grid must be a finite 3-D array (the fit diverged?), got shape {v.shape}")
    if not (v.min() < 0 < v.max()):
        where = "outside" if v.min() >= 0 else "inside"
        raise ReconstructionError(f"no surface: the SDF is {where} everywhere on the grid")
    sx, sy, sz = np.broadcast_to(np.asarray(spacing, float), (3,))
    verts, faces, _, _ = marching_cubes(v, level=0.0, spacing=(sz, sy, sx))
    verts = verts[:, ::-1] + np.asarray(origin, float)  # (z, y, x) -> (x, y, z)
    # Swapping the axes to (x, y, z) mirrors the frame: flip the winding so that normals point out of the solid.
    return trimesh.Trimesh(verts, faces[:, ::-1], process=True)


def mesh_from_field(field, resolution: int | None = None, floor_z: float | None = None, fill_under: bool = False,
                    open_m: float = 0.0, floater_fraction: float = 0.0, fill_pockets: bool = True):
    """Marching cubes of a GridField (cleaned by `clean_solid`, with the floor at height `floor_z` metres, if any,
    its closed pockets filled unless not `fill_pockets`),
    on its own nodes or resampled to `resolution` cells along its longest side, with vertex normals from the field's
    gradient (central differences). fill_under (a table at floor_z): fill the hidden space under overhangs first
    (`grid_ops.fill_under_overhangs`), less what a gap of over 2 `open_m` metres opens to the side.
    floater_fraction: remove solid pieces smaller than this fraction of the largest (FLOATER_FRACTION on a table)."""
    vals = field.sdf.detach()
    n = max(field.counts) - 1
    spacing = np.full(3, field.voxel)
    if resolution is not None and resolution != n:
        if not (isinstance(resolution, (int, np.integer)) and 8 <= resolution <= 1024):
            raise ReconstructionError(f"mesh resolution {resolution} must be an integer in [8, 1024]")
        factor = resolution / n
        size = tuple(max(2, int(round((c - 1) * factor)) + 1) for c in vals.shape[2:])  # (nz, ny, nx)
        with torch.no_grad():
            vals = torch.nn.functional.interpolate(vals, size=size, mode="trilinear", align_corners=True)
        ext = (np.array(vals.shape[2:][::-1]) - 1)  # cells along x, y, z
        spacing = (np.array(field.counts) - 1) * field.voxel / ext
    grid = vals[0, 0].cpu().numpy()
    below = below_floor(grid.shape, float(field.origin[2]), float(spacing[2]), floor_z)
    if below is not None and fill_under:
        z = node_heights(grid.shape[0], float(field.origin[2]), float(spacing[2]))
        grid = fill_under_overhangs(grid, z, floor_z, -0.5 * float(np.min(spacing)),
                                    open_nodes=open_nodes(open_m, float(np.min(spacing))))
    mesh = mesh_from_values(clean_solid(grid, floater_fraction, below, fill_pockets), field.origin.cpu().numpy(),
                            spacing)
    mesh.vertex_normals = vertex_normals(field, mesh.vertices)
    return mesh


def vertex_normals(field, points: np.ndarray, chunk: int = 1 << 16) -> np.ndarray:
    """Unit gradients (N, 3) of a GridField at points (N, 3) metres, by central differences of half a voxel."""
    out = np.zeros((len(points), 3))
    h = 0.5 * field.voxel
    eye = torch.eye(3, dtype=field.sdf.dtype, device=field.sdf.device) * h
    with torch.no_grad():
        for i in range(0, len(points), chunk):
            p = torch.as_tensor(points[i: i + chunk], dtype=field.sdf.dtype, device=field.sdf.device)
            v = field.sample(torch.cat([p[:, None] + eye, p[:, None] - eye], dim=1))
            out[i: i + chunk] = (v[:, :3] - v[:, 3:]).double().cpu().numpy()
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)


__all__ = ["FLOATER_FRACTION", "clean_solid", "mesh_from_values", "mesh_from_field", "vertex_normals"]
