"""A watertight triangle mesh of a signed distance function (sdf.py): marching cubes on a grid that evaluates the
function exactly only near its surface.

The grid is built coarse to fine. A node of a finer level takes the value of its nearest coarser node, shrunk by
LIPSCHITZ x their distance, when that still leaves it clearly away from the surface (|f| >= two voxel diagonals);
only the other nodes are evaluated. The sign of every node is right and the nodes of every cell the surface crosses
are exact, which is all marching cubes reads, at a few % of the cost of evaluating the whole grid.

The grid's nodes sit half a voxel off z = 0, so the floor cut `max(f, -z)` puts the object's flat base exactly on
z = 0 and marching cubes never meets a node on the surface there.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import MeshError
from .sdf import Shape

LIPSCHITZ = 2.0
"""How much faster than the distance a shape's field may change (1 for exact distances; the ellipsoid bound and the
smooth union stay well under 2)."""
TOP_LEVEL = 8
"""The coarsest level's node spacing, in voxels (a power of two)."""


def mesh_sdf(shape: Shape, half_xy: float, height: float, voxel: float):
    """The surface f = 0 of `shape` cut at z = 0, within |x|, |y| <= half_xy and 0 <= z <= height (metres), meshed
    with voxels of `voxel` metres; returned as a new trimesh.Trimesh moved so that its bounding box is centred on
    the z axis. A one-line MeshError when the solid reaches the box's walls or is empty."""
    import trimesh
    from skimage.measure import marching_cubes

    if not (voxel > 0 and half_xy > 0 and height > 0):
        raise MeshError(f"mesh_sdf needs a positive box and voxel, got half_xy {half_xy}, height {height}, "
                        f"voxel {voxel}")
    pad = 2
    n_xy = int(math.ceil(half_xy / voxel)) + pad
    xs = (np.arange(-n_xy, n_xy) + 0.5) * voxel
    zs = (np.arange(-pad, int(math.ceil(height / voxel)) + pad) + 0.5) * voxel

    def cut(x, y, z):
        return np.maximum(shape(x, y, z), -z)

    values = grid_values(cut, xs, xs, zs, voxel)
    border = np.concatenate([a.ravel() for a in (values[0], values[-1], values[:, 0], values[:, -1],
                                                 values[:, :, 0], values[:, :, -1])])
    if np.any(border <= 0):
        raise MeshError(f"the solid reaches the meshing box (|x|, |y| <= {half_xy} m, 0 <= z <= {height} m)")
    if not np.any(values < 0):
        raise MeshError("the shape holds no solid inside the meshing box")
    # A node on (or a hair from) the surface makes marching cubes put several vertices on one point, and triangles
    # of no area between them; moving such nodes a micrometre off the surface keeps every triangle proper.
    tiny = np.float32(1e-3 * voxel)
    on = np.abs(values) < tiny
    values[on] = np.where(values[on] < 0, -tiny, tiny)
    verts, faces, _, _ = marching_cubes(values, 0.0, spacing=(voxel, voxel, voxel))
    verts = verts + np.array([xs[0], xs[0], zs[0]])
    verts[np.abs(verts[:, 2]) < 1e-3 * voxel, 2] = 0.0  # the base: on z = 0 up to float rounding
    mesh = trimesh.Trimesh(verts, faces, process=False)  # one vertex per crossed grid edge already
    if mesh.volume < 0:
        mesh.invert()
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, 0.0])
    return mesh


def grid_values(shape: Shape, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray, voxel: float) -> np.ndarray:
    """(len(xs), len(ys), len(zs)) float32 values of `shape` on the grid: exact (in float32) within two voxel
    diagonals of its surface, elsewhere of the right sign and no larger in magnitude than the true value."""
    axes = [np.asarray(a, np.float32) for a in (xs, ys, zs)]
    step = TOP_LEVEL
    idx = [np.arange(0, len(a), step) for a in axes]
    values = shape(axes[0][idx[0]][:, None, None], axes[1][idx[1]][None, :, None],
                   axes[2][idx[2]][None, None, :]).astype(np.float32)
    near = np.float32(2.0 * voxel * math.sqrt(3.0))
    while step > 1:
        step //= 2
        idx = [np.arange(0, len(a), step) for a in axes]
        # A node's nearest coarser node is the parent level's j // 2: the same point for even j, `step` voxels
        # away along each axis where j is odd.
        odd = [(np.arange(len(i)) % 2).astype(np.float32) for i in idx]
        parent = values[np.ix_(*(np.arange(len(i)) // 2 for i in idx))]
        reach = np.sqrt(odd[0][:, None, None] + odd[1][None, :, None] + odd[2][None, None, :])
        bound = np.abs(parent) - np.float32(LIPSCHITZ * step * voxel) * reach
        values = np.copysign(np.maximum(bound, 0.0), parent)
        i, j, k = np.nonzero(bound < near)
        values[i, j, k] = shape(axes[0][idx[0][i]], axes[1][idx[1][j]], axes[2][idx[2][k]])
    return values


__all__ = ["mesh_sdf", "grid_values", "LIPSCHITZ"]
