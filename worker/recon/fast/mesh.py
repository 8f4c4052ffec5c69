"""Meshes from SDF grids: marching cubes at the zero level, in world metres."""

from __future__ import annotations

import numpy as np
import torch

from spadscan.protocol.errors import ConfigError


def clean_solid(values: np.ndarray, min_fraction: float = 0.005) -> np.ndarray:
    """Remove what the histograms cannot have seen from an SDF grid (nz, ny, nx) -> cleaned copy.

    Cavities (empty regions not connected to the grid's boundary) lie behind every surface a sensor outside can see:
    they are filled. Solid pieces smaller than `min_fraction` of the largest piece (by node count) are floaters:
    they are emptied. Filled and emptied nodes get a value of half a node spacing's worth (+-1e-3 of the field's
    scale), so the surface moves only where something was removed.
    """
    from scipy import ndimage

    v = np.array(values, np.float32, copy=True)
    solid = v < 0
    if not solid.any():
        return v
    empty_lab, n_empty = ndimage.label(~solid)
    border = np.unique(np.concatenate([empty_lab[[0, -1]].ravel(), empty_lab[:, [0, -1]].ravel(),
                                       empty_lab[:, :, [0, -1]].ravel()]))
    cavity = (~solid) & ~np.isin(empty_lab, border[border > 0])
    eps = 1e-4 * max(float(np.abs(v).max()), 1e-6)
    v[cavity] = -eps
    lab, n = ndimage.label(v < 0)
    if n > 1:
        sizes = np.bincount(lab.ravel())[1:]
        small = np.flatnonzero(sizes < min_fraction * sizes.max()) + 1
        v[np.isin(lab, small)] = eps
    return v


def mesh_from_values(values: np.ndarray, origin, voxel: float):
    """Marching cubes of an SDF grid (nz, ny, nx) with nodes at origin + voxel * (x, y, z) -> trimesh.Trimesh.

    A grid with no zero crossing gives an empty mesh (no vertices) rather than an error.
    """
    import trimesh
    from skimage.measure import marching_cubes

    v = np.asarray(values, np.float32)
    if v.ndim != 3 or not np.all(np.isfinite(v)):
        raise ConfigError(f"SDF grid must be a finite 3-D array, got shape {v.shape}")
    if not (v.min() < 0 < v.max()):
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
    verts, faces, _, _ = marching_cubes(v, level=0.0, spacing=(voxel, voxel, voxel))
    verts = verts[:, ::-1] + np.asarray(origin, float)  # (z, y, x) -> (x, y, z)
    # marching_cubes orients faces for a field increasing outward when the axes are (z, y, x); swapping to
    # (x, y, z) mirrors the frame, so flip the winding to keep normals pointing out of the solid.
    return trimesh.Trimesh(verts, faces[:, ::-1], process=True)


def mesh_from_field(field, resolution: int | None = None):
    """Marching cubes of a GridField, on its own nodes or resampled to `resolution` nodes on the longest side."""
    vals = field.sdf.detach()
    voxel = field.voxel
    if resolution is not None and resolution != max(field.counts):
        if not (isinstance(resolution, int) and 8 <= resolution <= 1024):
            raise ConfigError(f"mesh resolution {resolution} must be an integer in [8, 1024]")
        factor = (resolution - 1) / (max(field.counts) - 1)
        size = tuple(max(2, int(round((n - 1) * factor)) + 1) for n in vals.shape[2:])
        with torch.no_grad():
            vals = torch.nn.functional.interpolate(vals, size=size, mode="trilinear", align_corners=True)
        voxel = voxel / factor
    return mesh_from_values(clean_solid(vals[0, 0].cpu().numpy()), field.origin.cpu().numpy(), voxel)


__all__ = ["mesh_from_values", "mesh_from_field"]
