"""Surfaces from SDFs: marching cubes (scikit-image) on a grid over the scene box, normals from the SDF gradient."""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
import trimesh
from skimage.measure import marching_cubes

from ..errors import ReconstructionError


def sdf_grid(sdf: Callable[[torch.Tensor], torch.Tensor], box: torch.Tensor, resolution: int,
             chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate sdf (N, 3) -> (N,) on a grid over box (2, 3) with `resolution` cells along the longest side.

    Returns (values (nx, ny, nz) float32, spacing (3,) metres); grid point (i, j, k) sits at box[0] + (i, j, k) *
    spacing."""
    if not (isinstance(resolution, int) and 8 <= resolution <= 1024):
        raise ReconstructionError(f"mesh resolution {resolution} must be an integer in [8, 1024]")
    lo, hi = box[0].double().cpu(), box[1].double().cpu()
    step = float((hi - lo).max()) / resolution
    counts = [max(2, int(np.ceil(float(hi[i] - lo[i]) / step)) + 1) for i in range(3)]
    axes = [lo[i] + step * torch.arange(counts[i], dtype=torch.float64) for i in range(3)]
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    out = np.empty(pts.shape[0], np.float32)
    with torch.no_grad():
        for i in range(0, pts.shape[0], chunk):
            p = pts[i:i + chunk].to(device=box.device, dtype=box.dtype)
            out[i:i + chunk] = sdf(p).detach().float().cpu().numpy()
    return out.reshape(counts), np.full(3, step)


def marching_cubes_mesh(sdf: Callable[[torch.Tensor], torch.Tensor],
                        grad: Callable[[torch.Tensor], torch.Tensor] | None, box: torch.Tensor, resolution: int):
    """The zero level set of `sdf` inside `box` as a trimesh.Trimesh with per-vertex normals.

    grad: (N, 3) -> (N, 3) SDF gradient for the normals (None: the mesh's own). Raises ReconstructionError when the
    field has no zero crossing in the box (all inside or all outside) or is not finite."""
    values, spacing = sdf_grid(sdf, box, resolution)
    if not np.all(np.isfinite(values)):
        raise ReconstructionError("the SDF is not finite on the mesh grid (the fit diverged)")
    if values.min() >= 0 or values.max() <= 0:
        where = "outside" if values.min() >= 0 else "inside"
        raise ReconstructionError(f"no surface: the SDF is {where} everywhere in the scene box "
                                  f"(min {values.min():.3g} m, max {values.max():.3g} m)")
    verts, faces, _, _ = marching_cubes(values, level=0.0, spacing=tuple(spacing))
    verts = verts + box[0].double().cpu().numpy()
    # marching_cubes orients faces for increasing values = outward for an SDF; trimesh wants counter-clockwise out.
    mesh = trimesh.Trimesh(verts, faces[:, ::-1], process=False)
    if grad is not None:
        normals = np.zeros_like(verts)
        for i in range(0, len(verts), 65536):
            p = torch.as_tensor(verts[i:i + 65536], dtype=box.dtype, device=box.device)
            normals[i:i + 65536] = grad(p).detach().double().cpu().numpy()
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        mesh.vertex_normals = normals
    return mesh
