"""Is the reconstructed mesh in one piece (worker/pieces.py): pieces counted by their share of the surface, specks
left uncounted, a mesh without surface refused in one line."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from spadscan.protocol.errors import SpadscanError
from spadscan.worker.pieces import PIECE_MIN_SHARE, SPECKS_LIMIT, mesh_pieces


def box(size, x=0.0):
    return trimesh.creation.box(extents=(size, size, size)).apply_translation([x, 0.0, size / 2])


def test_one_closed_surface_is_one_piece():
    pieces = mesh_pieces(trimesh.creation.icosphere(subdivisions=3, radius=0.05))
    assert (pieces.count, pieces.share_apart, pieces.specks) == (1, 0.0, 0)


def test_two_pieces_apart_are_counted_with_the_share_outside_the_largest():
    # Faces: a 10 cm cube (600 cm^2) and a 5 cm one (150 cm^2) 20 cm away: a fifth of the area is apart.
    pieces = mesh_pieces(trimesh.util.concatenate([box(0.1), box(0.05, x=0.2)]))
    assert pieces.count == 2 and pieces.specks == 0
    assert pieces.share_apart == pytest.approx(150 / 750)


def test_pieces_that_touch_at_no_shared_edge_are_still_apart():
    # Two cubes face to face with a 0.1 mm gap: marching cubes' surfaces of a broken joint look like this.
    pieces = mesh_pieces(trimesh.util.concatenate([box(0.1), box(0.1, x=0.1001)]))
    assert pieces.count == 2 and pieces.share_apart == pytest.approx(0.5)


def test_a_speck_under_the_minimum_share_is_no_piece_but_counts_in_the_share():
    # A 1 mm cube beside a 10 cm one: 6 mm^2 of 60,006, far under PIECE_MIN_SHARE.
    pieces = mesh_pieces(trimesh.util.concatenate([box(0.1), box(0.001, x=0.2)]))
    assert pieces.count == 1 and pieces.specks == 1
    assert pieces.share_apart == pytest.approx(6 / 60_006) and pieces.share_apart < PIECE_MIN_SHARE
    assert pieces.specks_share == pytest.approx(pieces.share_apart)
    assert pieces.to_dict() == {"count": 1, "share_apart": pieces.share_apart, "specks": 1,
                                "specks_share": pieces.specks_share, "tunnels": 0, "min_share": PIECE_MIN_SHARE,
                                "specks_limit": SPECKS_LIMIT}


def test_a_piece_just_over_the_minimum_share_counts():
    # Side s beside a 10 cm cube so that it holds 1.5 * PIECE_MIN_SHARE of the area.
    share = 1.5 * PIECE_MIN_SHARE
    side = 0.1 * np.sqrt(share / (1 - share))
    pieces = mesh_pieces(trimesh.util.concatenate([box(0.1), box(side, x=0.2)]))
    assert pieces.count == 2 and pieces.share_apart == pytest.approx(share)


def test_a_mesh_without_surface_is_refused_in_one_line():
    with pytest.raises(SpadscanError, match="no surface"):
        mesh_pieces(trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), int)))
    flat = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [2, 0, 0]], faces=[[0, 1, 2]], process=False)
    with pytest.raises(SpadscanError, match="no surface"):
        mesh_pieces(flat)
