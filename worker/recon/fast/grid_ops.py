"""Operations on the nodes of an SDF grid (nz, ny, nx) that both the fit and the mesh use: node heights, what lies
under the floor, closed cavities and the hidden space under overhangs. numpy, metres."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


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


def under_overhangs(solid: np.ndarray, z_nodes: np.ndarray, floor_z: float) -> np.ndarray:
    """(nz, ny, nx) bool: the empty nodes of a solid grid that lie above the table (at floor_z) and below a solid node
    of their column. z_nodes (nz,): the nodes' heights, metres.

    Sensors look at a table-top object from above: the space between an object's underside and the table is
    hidden from every view (no histogram says whether it is empty), and an empty gap there is a fit that
    the data did not ask for — it is what the object's unseen bottom and the melted skirt leave behind."""
    solid = np.asarray(solid, bool)
    above_table = (np.asarray(z_nodes) >= floor_z)[:, None, None]
    # Solid at or above each node in its column: a cumulative OR from the top of the grid down.
    covered = np.flip(np.logical_or.accumulate(np.flip(solid, axis=0), axis=0), axis=0)
    return (~solid) & covered & above_table


def fill_under_overhangs(values: np.ndarray, z_nodes: np.ndarray, floor_z: float, fill_value: float) -> np.ndarray:
    """Copy of an SDF grid (nz, ny, nx) with the nodes `under_overhangs` made solid (`fill_value` < 0)."""
    v = np.array(values, np.float32, copy=True)
    v[under_overhangs(v < 0, z_nodes, floor_z)] = fill_value
    return v


__all__ = ["node_heights", "below_floor", "cavities", "under_overhangs", "fill_under_overhangs"]
