"""Cropping meshes to a box (`spadscan eval --box`, the cut above a table): faces that pass through the box are
clipped at its walls whatever their size, so a coarse ground truth and a fine copy of it are scored over the same
surface."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh

from spadscan.cli import main
from spadscan.protocol.errors import MeshError
from spadscan.worker.ground_truth import cut_above
from spadscan.worker.metrics import crop_to_box, mesh_metrics

N = 20_000
BAND = ([-0.2, -0.2, 0.12], [0.2, 0.2, 0.18])
"""A 6 cm band across the block's middle: each wall triangle passes through it with every corner and its centroid
outside."""
WALL_BAND = ([-0.2, -0.2, 0.1], [0.2, 0.2, 0.2])
"""A band whose walls pass through the block's wall triangles' centroids (z = 0.1 and 0.2)."""


def block():
    """A 10 x 10 x 30 cm block standing on z = 0: 12 large triangles, like a CAD file's."""
    return trimesh.creation.box([0.1, 0.1, 0.3]).apply_translation([0, 0, 0.15])


def fine(mesh, edge_m=0.003):
    out = mesh.subdivide_to_size(edge_m, max_iter=20)
    return trimesh.Trimesh(out.vertices, out.faces)


def float32(mesh):
    """The mesh as an STL holds it: its corners rounded to float32 (0.1 and 0.2 are not exact)."""
    return trimesh.Trimesh(mesh.vertices.astype(np.float32).astype(np.float64), mesh.faces, process=False)


def floor_mm(area_m2, n):
    return 0.5 * math.sqrt(area_m2 / n) * 1e3


def test_a_face_through_the_box_with_its_corners_and_centroid_outside_is_clipped():
    band = crop_to_box(block(), *BAND)
    assert band.area == pytest.approx(4 * 0.1 * 0.06, rel=1e-9)  # the four walls' strips, nothing else
    assert band.bounds[:, 2] == pytest.approx([0.12, 0.18], abs=1e-12)


@pytest.mark.parametrize("box", [BAND, WALL_BAND])
@pytest.mark.parametrize("copy", [fine, float32])
def test_a_mesh_scored_against_a_copy_of_itself_in_a_band_scores_the_floor(box, copy):
    gt = crop_to_box(block(), *box)
    recon = crop_to_box(copy(block()), *box)
    assert recon.area == pytest.approx(gt.area, rel=1e-6)
    m = mesh_metrics(recon, gt, n_points=N)
    assert m.chamfer_mm < 1.3 * floor_mm(gt.area, N) and m.fscore_5mm == 1.0


def test_eval_box_scores_a_mesh_against_itself_at_the_floor(tmp_path, capsys):
    block().export(tmp_path / "block.stl")
    fine(block()).export(tmp_path / "block_fine.ply")
    for name, box in (("block_fine.ply", BAND), ("block.stl", WALL_BAND)):
        rc = main(["eval", str(tmp_path / name), "--gt", "builtin:tall-block", "--json", "--points", str(N),
                   "--box", *map(str, box[0] + box[1])])
        captured = capsys.readouterr()
        assert rc == 0, captured.err
        area = 4 * 0.1 * (box[1][2] - box[0][2])
        assert json.loads(captured.out)["chamfer_mm"] < 1.3 * floor_mm(area, N)


def test_clipped_pieces_keep_their_winding_and_stay_connected_along_the_walls():
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    part = crop_to_box(ball, [-1, -1, 0.013], [0.05, 1, 1])
    outward = np.einsum("ij,ij->i", part.face_normals, part.triangles_center)
    assert np.all(outward > 0)
    edges, count = np.unique(np.sort(part.edges, axis=1), axis=0, return_counts=True)
    assert count.max() == 2
    rim = part.vertices[edges[count == 1]]  # edges of one face only: the cut, nowhere else
    assert np.all(np.isclose(rim[:, :, 2], 0.013) | np.isclose(rim[:, :, 0], 0.05))


def test_the_cut_above_a_table_is_the_same_for_a_coarse_and_a_fine_mesh():
    coarse, thin = cut_above(block(), 0.1234), cut_above(fine(block()), 0.1234)
    area = 0.1 * 0.1 + 4 * 0.1 * (0.3 - 0.1234)
    assert coarse.area == pytest.approx(area, rel=1e-9) and thin.area == pytest.approx(area, rel=1e-9)
    assert coarse.bounds[0, 2] == pytest.approx(0.1234, abs=1e-12)


def test_a_face_on_a_wall_counts_as_inside_and_nothing_inside_is_an_error():
    side = crop_to_box(block(), [0.05, -1, -1], [1, 1, 1])  # the +x wall lies on the box's wall
    assert side.area == pytest.approx(0.1 * 0.3)
    with pytest.raises(MeshError, match=r"^ground truth: no triangle lies inside the crop box"):
        crop_to_box(block(), [0.06, -1, -1], [1, 1, 1], what="ground truth")


@pytest.mark.parametrize("which,gt_box", [("the ground truth", True), ("the mesh", False)])
def test_eval_box_says_which_mesh_has_nothing_inside(tmp_path, capsys, which, gt_box):
    far = block().apply_translation([1.0, 0, 0])
    (far if gt_box else block()).export(tmp_path / "gt.ply")
    (block() if gt_box else far).export(tmp_path / "recon.ply")
    box = ["-0.2", "-0.2", "0.1", "0.2", "0.2", "0.2"]
    assert main(["eval", str(tmp_path / "recon.ply"), "--gt", str(tmp_path / "gt.ply"), "--box", *box]) == 1
    err = capsys.readouterr().err
    named = tmp_path / ("gt.ply" if gt_box else "recon.ply")
    assert err.startswith(f"spadscan: error: {which} {named}: no triangle lies inside the crop box")
    assert err.count("\n") == 1
