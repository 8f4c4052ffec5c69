"""Operations on the nodes of an SDF grid (nz, ny, nx) that both the fit and the mesh use: node heights, what lies
under the floor, closed cavities and the hidden space under overhangs. numpy, metres."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .grid_field import signed_distance


def node_heights(nz: int, origin_z: float, spacing_z: float) -> np.ndarray:
    """(nz,) heights (metres) of a grid's node rows: row k at origin_z + k * spacing_z."""
    return origin_z + np.arange(nz) * spacing_z


def below_floor(shape: tuple[int, int, int], origin_z: float, spacing_z: float, floor_z: float | None):
    """(nz, ny, nx) bool view: the nodes of a grid (rows at `node_heights`) that lie under the floor at floor_z;
    None when there is no floor."""
    if floor_z is None:
        return None
    z = node_heights(shape[0], origin_z, spacing_z)
    return np.broadcast_to((z < floor_z)[:, None, None], shape)


def cavities(solid: np.ndarray, below_floor: np.ndarray | None = None) -> np.ndarray:
    """Empty nodes of a boolean grid (nz, ny, nx) that no path through empty nodes links to the grid's boundary.

    below_floor: nodes under the floor the object stands on (or None); they count as solid, since no sensor sees from
    under the floor: a pocket closed by the object and the floor is as hidden as one closed by the object alone."""
    wall = solid if below_floor is None else (solid | below_floor)
    empty_lab, _ = ndimage.label(~wall)
    border = np.unique(np.concatenate([empty_lab[[0, -1]].ravel(), empty_lab[:, [0, -1]].ravel(),
                                       empty_lab[:, :, [0, -1]].ravel()]))
    return (~wall) & ~np.isin(empty_lab, border[border > 0])


def under_overhangs(solid: np.ndarray, z_nodes: np.ndarray, floor_z: float, open_nodes: int = 0) -> np.ndarray:
    """(nz, ny, nx) bool: the empty nodes of a solid grid that lie above the table (at floor_z) and below a solid node
    of their column, less those that an opening at least 2 `open_nodes` + 1 nodes wide joins to the space around
    the object (`open_to_outside`; 0: none left out). z_nodes (nz,): the nodes' heights, metres.

    Sensors look at a table-top object from above: the space between an object's underside and the table is
    hidden from every view (no histogram says whether it is empty), and an empty gap there is a fit that
    the data did not ask for — it is what the object's unseen bottom and the melted skirt leave behind. Space under
    an overhang that a wide gap opens to the side is not hidden: the views from the side see into it (the neck
    under a head standing on a can)."""
    solid = np.asarray(solid, bool)
    above_table = (np.asarray(z_nodes) >= floor_z)[:, None, None]
    # Solid at or above each node in its column: a cumulative OR from the top of the grid down.
    covered = np.flip(np.logical_or.accumulate(np.flip(solid, axis=0), axis=0), axis=0)
    under = (~solid) & covered & above_table
    if open_nodes > 0 and under.any():
        under &= ~open_to_outside((~solid) & above_table, open_nodes)
    return under


def redistanced(values: np.ndarray, voxel: float) -> np.ndarray:
    """The grid `values` (nz, ny, nx, metres) made a signed distance again away from its zero level: a node with a
    neighbour of the other sign keeps its value, clamped to a voxel (the surface's sub-voxel position); every other
    node gets its distance (metres) to the nearest node of the other sign less half a voxel, negative inside
    (`grid_field.signed_distance` of the solid nodes). Same shape and dtype; the sign of every node is kept."""
    if not voxel > 0:
        raise ValueError(f"voxel {voxel} m must be > 0")
    inside = values < 0
    if inside.all() or not inside.any():
        return values.copy()
    far = signed_distance(inside, voxel)
    # A face neighbour of the other sign puts a node half a voxel from the zero level; the next nearest, a diagonal
    # one, 0.91 voxel.
    at_surface = np.abs(far) < 0.7 * voxel
    near = np.clip(values, -voxel, voxel)
    return np.where(at_surface, near, far).astype(values.dtype)


def open_nodes(width_m: float, voxel_m: float) -> int:
    """`under_overhangs`'s open_nodes for a gap half-width of `width_m` metres on a grid of `voxel_m` metre cells: the
    fit and the mesh convert it alike, so that the mesh keeps open what the fit kept open."""
    return int(round(width_m / voxel_m))


def open_to_outside(empty: np.ndarray, width: int) -> np.ndarray:
    """(nz, ny, nx) bool: the `empty` nodes that passages at least 2 `width` + 1 nodes wide link to the grid's
    boundary: the empty space's morphological opening (erode by `width` nodes, keep what still reaches the
    boundary, dilate back), within the empty space."""
    cross = ndimage.generate_binary_structure(3, 1)
    pad = width + 1
    # The boundary is open: a shell of empty nodes around the grid, thicker than the erosion, keeps it so.
    space = np.pad(np.asarray(empty, bool), pad, constant_values=True)
    core = ndimage.binary_erosion(space, cross, iterations=width)
    labels, _ = ndimage.label(core)
    shell = np.ones(space.shape, bool)
    shell[pad:-pad, pad:-pad, pad:-pad] = False
    ids = np.unique(labels[shell & core])
    outside = np.isin(labels, ids[ids > 0])  # what still reaches the shell: the space around the object
    reached = ndimage.binary_dilation(outside, cross, iterations=width) & space
    return reached[pad:-pad, pad:-pad, pad:-pad]


def fill_under_overhangs(values: np.ndarray, z_nodes: np.ndarray, floor_z: float, fill_value: float,
                         open_nodes: int = 0) -> np.ndarray:
    """Copy of an SDF grid (nz, ny, nx) with the nodes `under_overhangs` made solid (`fill_value` < 0)."""
    v = np.array(values, np.float32, copy=True)
    v[under_overhangs(v < 0, z_nodes, floor_z, open_nodes)] = fill_value
    return v


__all__ = ["node_heights", "below_floor", "cavities", "under_overhangs", "redistanced", "open_nodes", "open_to_outside",
           "fill_under_overhangs"]
