"""The empty-space bias of scenes on a table: what no view can decide is left empty, not solid.

Space carving removes only what some zone proves empty. With no table behind the object (the simulated scenes), a
zone that looks past the object sees nothing and proves its whole field of view empty, so the hull hugs the object.
On a table it does not: a zone's first return is the object or the table, so the layer just above the table (within
the pulse's length of it, ~4 cm for the TMF8820) is never proven empty, and space near the edge of the views' fields
of view is barely looked at. That hull stays solid in the fit: the histograms cannot tell a low skirt on the table
from the table itself. Measured on LCSPCData's real pyramid, the skirt was most of the error (accuracy 23 mm against
completeness 4.6 mm).

So, with a table, every step pushes the surface inward on the surface nodes that few views look at (`coverage`
below `full_coverage`), by a fraction of the data gradient's rms: the data term holds a surface it sees, and what it
cannot see melts away. Nodes that most views look at get no push (their surface is the data's to place), which also
keeps the bias from digging into the object's unseen interior; pockets the solid closes are filled (`mesh.cavities`),
and so is the space under the solid (`under_overhangs`), which no view from above sees into.

What the push leaves of the skirt are thin curtains standing on the table: views from above see a vertical sheet edge
on, and within a pulse width of the table no histogram tells it from the table. Every few steps, sheets thinner than
a few voxels in that band are emptied (`thin_near_table`).
"""

from __future__ import annotations

import numpy as np
import torch


def view_coverage(points: torch.Tensor, poses: torch.Tensor, zones, chunk: int = 1 << 16) -> torch.Tensor:
    """Fraction of the views whose field of view (the union of its zones, occlusion ignored) holds each point.

    points (..., 3) and poses (V, 4, 4) sensor-to-world, metres; zones: the sensor model's Zone records (+z is the
    boresight). Returns (...) in [0, 1].
    """
    flat = points.reshape(-1, 3)
    rot, org = poses[:, :3, :3].to(flat.dtype), poses[:, :3, 3].to(flat.dtype)
    out = torch.empty(flat.shape[0], dtype=flat.dtype, device=flat.device)
    for i in range(0, flat.shape[0], chunk):
        rel = torch.einsum("vji,pvj->pvi", rot, flat[i: i + chunk, None, :] - org[None])  # sensor frame (P, V, 3)
        z = rel[..., 2]
        front = z > 1e-9
        tz = torch.where(front, z, torch.ones_like(z))
        seen = torch.zeros(z.shape, dtype=torch.bool, device=flat.device)
        for zone in zones:
            if zone.kind == "rect":
                tx, ty = rel[..., 0] / tz, rel[..., 1] / tz
                seen |= (front & (tx >= zone.tan_x[0]) & (tx <= zone.tan_x[1]) & (ty >= zone.tan_y[0])
                         & (ty <= zone.tan_y[1]))
            else:
                axis = torch.as_tensor(zone.axis, dtype=rel.dtype, device=rel.device)
                cos = (rel @ axis) / rel.norm(dim=-1).clamp(min=1e-12)
                seen |= cos >= float(np.cos(zone.half_angle_rad))
        out[i: i + chunk] = seen.to(flat.dtype).mean(dim=1)
    return out.reshape(points.shape[:-1])


def pressure_weight(coverage: torch.Tensor, full_coverage: float) -> torch.Tensor:
    """1 where no view looks, falling linearly to 0 where `full_coverage` (a fraction of the views) or more look."""
    if not 0 < full_coverage <= 1:
        from spadscan.protocol.errors import ConfigError

        raise ConfigError(f"pressure coverage {full_coverage} must be in (0, 1]")
    return (1.0 - coverage / full_coverage).clamp(0.0, 1.0)


def push_to_empty(grad: torch.Tensor, sdf: torch.Tensor, voxel: float, weight: torch.Tensor, strength: float) -> None:
    """Add the empty-space push to a grid's gradient in place: on surface nodes (|sdf| < one voxel), minus
    `strength` x the gradient's rms over those nodes x `weight` (a descent step then raises the SDF: less solid).

    grad, sdf, weight: grids of one shape (1, 1, nz, ny, nx); voxel in metres."""
    surf = sdf.detach().abs() < voxel
    if not bool(surf.any()):
        return
    rms = torch.sqrt((grad[surf] ** 2).mean())
    if not bool(torch.isfinite(rms)) or float(rms) == 0.0:
        return
    grad -= strength * rms * surf.to(grad.dtype) * weight


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


def thin_near_table(solid: np.ndarray, z_nodes: np.ndarray, floor_z: float, band_m: float, radius: int) -> np.ndarray:
    """(nz, ny, nx) bool: the solid nodes less than `band_m` above the table (at floor_z) that a morphological opening
    of `radius` node steps removes — sheets and fins thinner than about 2 x radius nodes. z_nodes (nz,): heights of
    the node rows, metres, increasing; the space under the table counts as solid, so the object's base is not eroded
    from below.

    Near the table the histograms cannot tell a thin sheet from the table behind it, and views from above see a
    vertical sheet edge on: such curtains are what the carved hull's skirt melts into, and nothing in the data
    removes them (on LCSPCData's real pyramid, a fifth of the surface lay 1-3 cm outside the object, in curtains up
    to 8 cm high; `field.thin_sheet_band_m` sets band_m)."""
    from scipy import ndimage

    out = np.zeros(solid.shape, bool)
    z = np.asarray(z_nodes, np.float64)
    in_band = (z >= floor_z) & (z < floor_z + band_m)
    if radius <= 0 or not in_band.any():
        return out
    # The opening reaches 2 x radius rows: a slab that far above the band gives exact answers inside it.
    top = min(len(z), int(np.flatnonzero(in_band)[-1]) + 2 * radius + 2)
    wall = solid[:top] | (z[:top] < floor_z)[:, None, None]
    cross = ndimage.generate_binary_structure(3, 1)
    opened = ndimage.binary_opening(wall, structure=cross, iterations=radius)
    out[:top] = solid[:top] & ~opened & in_band[:top, None, None]
    return out


__all__ = ["view_coverage", "pressure_weight", "push_to_empty", "under_overhangs", "fill_under_overhangs",
           "thin_near_table"]
