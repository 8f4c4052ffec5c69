"""Is the reconstructed mesh in one piece? Where it is not, and the object is, parts of the fit broke off.

A fit at the grid's resolution breaks a part thinner than about two of its cells (a stool's 12 mm legs on a 5 mm
grid) into fragments, and a wrong fit can leave lumps of surface standing apart from the object (phantoms on a
table). Neither shows in the fit's misfit: what breaks is thin and returns few photons. Both show in the mesh
itself as surface apart from its largest connected piece. Marching cubes also leaves specks of a few faces around a
good surface; they hold a negligible share of the area, so the share, not the count, is what is judged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from spadscan.protocol.errors import SpadscanError

PIECE_MIN_SHARE = 0.01
"""Share of the surface area a connected piece must hold to be counted as a piece. The specks that marching cubes
leaves beside a surface hold none of it that shows (0.000 % on all of 175 fits under 2 mm measured,
docs/end_of_run.md); a mug's handle that came off holds 3-4 %, a piece of a stool's broken leg 8 %. Since meshes
without a table keep their small pieces, a good fit's specks hold up to 1 % together (the demo goblet, the snowman),
each far under the limit."""

SPECKS_LIMIT = 0.015
"""Share of the surface the specks may hold together before the result says so (end_of_run.specks_warning): twice
the largest share among 24 good fits (0.72 %, a mug at 1.90 mm) and half a 3 cm cube's spiky fit's (3.0-3.4 %;
docs/end_of_run.md, "Specks")."""


@dataclass
class Pieces:
    """The mesh's connected pieces (faces joined by shared edges), summarised by surface area."""

    count: int
    """Pieces holding at least PIECE_MIN_SHARE of the surface area."""
    share_apart: float
    """Share of the surface area outside the largest piece (specks included): 0 for a mesh in one piece."""
    specks: int
    """Pieces smaller than PIECE_MIN_SHARE."""
    specks_share: float = 0.0
    """Share of the surface area the specks hold together."""
    tunnels: int | None = None
    """Tunnels through the pieces of note (their genus summed: a mug's handle is one, a hole through a wall one), or
    None where a piece of note is not closed and has no genus."""

    def to_dict(self) -> dict:
        return {"count": self.count, "share_apart": self.share_apart, "specks": self.specks,
                "specks_share": self.specks_share, "tunnels": self.tunnels, "min_share": PIECE_MIN_SHARE,
                "specks_limit": SPECKS_LIMIT}


def mesh_pieces(mesh: trimesh.Trimesh) -> Pieces:
    """The connected pieces of `mesh` (any units: only area shares are returned). SpadscanError for a mesh without
    surface."""
    if len(mesh.faces) == 0 or not mesh.area > 0:
        raise SpadscanError("pieces: the mesh has no surface")
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    areas = np.bincount(labels, weights=mesh.area_faces)
    shares = areas / areas.sum()
    small = shares < PIECE_MIN_SHARE
    return Pieces(count=max(int((~small).sum()), 1), share_apart=float(1.0 - shares.max()), specks=int(small.sum()),
                  specks_share=float(shares[small].sum()), tunnels=_tunnels(mesh, labels, np.flatnonzero(~small)))


def _tunnels(mesh: trimesh.Trimesh, labels: np.ndarray, pieces: np.ndarray) -> int | None:
    """The genus g = (2 - V + E - F) / 2 summed over `pieces` (labels of connected face sets), or None when one of
    them is not closed (an edge not on exactly two of its faces: an open surface has no genus). A fit's surface is
    closed unless it meets the grid's box."""
    edges = mesh.faces_unique_edges
    total = 0
    for piece in pieces:
        faces = np.flatnonzero(labels == piece)
        piece_edges, uses = np.unique(edges[faces], return_counts=True)
        if not np.all(uses == 2):
            return None
        euler = len(np.unique(mesh.faces[faces])) - len(piece_edges) + len(faces)
        total += max((2 - euler) // 2, 0)
    return total


__all__ = ["Pieces", "mesh_pieces", "PIECE_MIN_SHARE", "SPECKS_LIMIT"]
