"""Ground truth that includes the table the object stands on: the table is found, and the object above it scored."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from spadscan.protocol.errors import MeshError
from spadscan.worker.ground_truth import (CUT_ABOVE_TABLE_M, GroundTruth, load_ground_truth, object_on_table,
                                          table_top_z)

TOP = -0.156  # LCSPCData's pyramid table: a 2 m slab whose top is at this height (metres)


def pyramid(height=0.2, half=0.08):
    """A square pyramid standing on z = TOP."""
    base = [[-half, -half, TOP], [half, -half, TOP], [half, half, TOP], [-half, half, TOP]]
    mesh = trimesh.Trimesh(base + [[0, 0, TOP + height]], [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4], [0, 2, 1],
                                                           [0, 3, 2]])
    mesh.fix_normals()
    return mesh


def on_slab(obj):
    slab = trimesh.creation.box([2.0, 2.0, 0.1]).apply_translation([0, 0, TOP - 0.05])
    return trimesh.util.concatenate([slab, obj])


def test_the_table_top_is_the_upward_level_that_holds_most_of_the_area():
    assert table_top_z(on_slab(pyramid())) == pytest.approx(TOP)
    assert table_top_z(pyramid()) is None  # its base faces down
    assert table_top_z(trimesh.creation.box([0.1, 0.1, 0.1])) is None  # a top face holds 1/6 of a box
    assert table_top_z(trimesh.creation.icosphere()) is None


def test_a_flat_top_with_nothing_on_it_is_no_table():
    """A wide flat top that holds most of the area (a stool's seat, a low wide slab alone) has nothing standing on it:
    it is the object, not a table under one."""
    seat = trimesh.creation.box([0.4, 0.4, 0.02])
    seat.apply_translation([0, 0, 0.2])
    leg = trimesh.creation.box([0.02, 0.02, 0.2])
    leg.apply_translation([0, 0, 0.1])
    stool = trimesh.util.concatenate([seat, leg])
    assert table_top_z(stool) is None
    assert table_top_z(on_slab(stool)) == pytest.approx(TOP)


def test_the_object_above_the_table_is_what_is_scored():
    truth = object_on_table(on_slab(pyramid()))
    assert truth.cut_above_z_m == pytest.approx(TOP + CUT_ABOVE_TABLE_M)
    # Whole triangles are kept by their centroids, after a split to 2 mm.
    assert truth.mesh.bounds[0, 2] >= truth.cut_above_z_m - 0.002 and truth.mesh.area < pyramid().area
    # A reconstruction (finely tessellated, as marching cubes makes them) of the pyramid, with a skirt on the table
    # under the cut: it scores as the pyramid alone, at the sampling floor.
    fine = pyramid().subdivide_to_size(0.002, max_iter=12)
    skirt = trimesh.creation.box([0.3, 0.3, 0.002]).apply_translation([0, 0, TOP + 0.001])
    m = truth.metrics(trimesh.util.concatenate([fine, skirt]), n_points=20_000)
    floor_mm = 0.5 * np.sqrt(truth.mesh.area / 20_000) * 1e3  # two samplings of one surface lie this far apart
    assert m.chamfer_mm < 1.2 * floor_mm, m
    whole = GroundTruth(on_slab(pyramid())).metrics(trimesh.util.concatenate([fine, skirt]), n_points=20_000)
    assert whole.completeness_mm > 100  # scored whole, the slab swamps it
    # The same pyramid 4 mm off in x is scored as such.
    assert truth.metrics(fine.copy().apply_translation([0.004, 0, 0]), n_points=20_000).chamfer_mm > m.chamfer_mm + 1
    assert "table top + 5 mm" in truth.note() and GroundTruth(pyramid()).note() is None


def test_the_surface_above_the_cut_is_scored_whole_whatever_its_triangles():
    """A 12 mm block on the slab, stored as a CAD file does, two triangles a side: each side's lower triangle has its
    centroid under the cut (5 mm above the table), and whole triangles were kept by their centroids before the
    split: 4.9 of the 52.8 cm^2 above the cut were lost, and an exact reconstruction of the block scored half as
    much again as two samplings of one surface do."""
    block = trimesh.creation.box([0.06, 0.06, 0.012]).apply_translation([0, 0, TOP + 0.006])
    truth = object_on_table(on_slab(block))
    above = 0.06 * 0.06 + 4 * 0.06 * (0.012 - CUT_ABOVE_TABLE_M)
    assert truth.mesh.area == pytest.approx(above, rel=0.01)
    fine = block.subdivide_to_size(0.001, max_iter=12)
    assert truth.scored(fine).area == pytest.approx(above, rel=0.01)
    assert truth.scored(block).area == pytest.approx(above, rel=0.01), "the same surface, coarse, is cut alike"


def test_a_ground_truth_wound_inside_out_finds_its_table_all_the_same():
    """Its slab's bottom read as the table top: the cut went under the slab and the whole 2 m slab was scored."""
    mesh = on_slab(pyramid())
    inverted = trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
    assert table_top_z(inverted) == pytest.approx(TOP)


def test_a_ground_truth_without_a_table_is_scored_whole(tmp_path):
    ball = trimesh.creation.icosphere(radius=0.05).apply_translation([0, 0, 0.05])
    ball.export(tmp_path / "ball.ply")
    truth = load_ground_truth(tmp_path / "ball.ply")
    assert truth.cut_above_z_m is None and len(truth.mesh.faces) == len(ball.faces)
    assert truth.scored(ball) is ball
    on_slab(pyramid()).export(tmp_path / "scene.ply")
    assert load_ground_truth(tmp_path / "scene.ply").cut_above_z_m == pytest.approx(TOP + CUT_ABOVE_TABLE_M)
    kept = load_ground_truth(tmp_path / "scene.ply", keep_table=True)
    assert kept.cut_above_z_m is None and np.isclose(kept.mesh.area, on_slab(pyramid()).area)
    assert load_ground_truth("builtin:cup").cut_above_z_m is None


def test_a_reconstruction_with_nothing_above_the_cut_is_a_one_line_error_that_names_it():
    truth = object_on_table(on_slab(pyramid()))
    flat = trimesh.creation.box([0.2, 0.2, 0.004]).apply_translation([0, 0, TOP + 0.002])
    with pytest.raises(MeshError, match=r"nothing above z = -0\.1510 m.*table top \+ 5 mm") as info:
        truth.metrics(flat, n_points=1000)
    assert "\n" not in str(info.value)


def test_the_ground_truth_a_manifest_names(tmp_path):
    from spadscan.worker.ground_truth import capture_ground_truth, named_ground_truth

    mesh = tmp_path / "gt.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert named_ground_truth({"scene": {"ground_truth": str(mesh)}}) == (str(mesh), None)
    assert named_ground_truth({"scene": {"builtin": "sphere"}}) == ("builtin:sphere", None)
    # The first one that loads wins; the reason the first failed is kept only when none loads.
    assert named_ground_truth({"scene": {"ground_truth": str(tmp_path / "x.ply"), "builtin": "cup"}}) == (
        "builtin:cup", None)
    spec, why = named_ground_truth({"scene": {"mesh": str(tmp_path / "x.ply"), "builtin": "nope"}})
    assert spec is None and why == f"{tmp_path / 'x.ply'}: no such ground-truth mesh; no metrics"
    for manifest in ({}, {"scene": None}, {"scene": {"mesh": 3}}, []):
        assert named_ground_truth(manifest) == (None, None)
    assert capture_ground_truth(tmp_path / "not-a-capture") == (None, None)


def test_a_scene_placed_with_an_offset_is_scored_where_it_stood(tmp_path):
    import json

    import trimesh

    from spadscan.worker.ground_truth import capture_ground_truth, scene_offset_m
    from spadscan.worker.jobs import ground_truth

    manifest = {"scene": {"builtin": "sphere", "mesh_offset_m": [0.1, 0.0, 0.02]}}
    assert scene_offset_m(manifest).tolist() == [0.1, 0.0, 0.02]
    assert scene_offset_m({"scene": {"builtin": "sphere", "mesh_offset_m": [0, 0, 0]}}) is None
    path, note = ground_truth(manifest, tmp_path)
    assert note is None and path == tmp_path / "ground_truth.ply"
    from spadscan.protocol.scenes import builtin_scene

    moved, still = trimesh.load(path), builtin_scene("sphere")
    assert abs(moved.bounds - (still.bounds + [0.1, 0.0, 0.02])).max() < 1e-6
    # A command reading the capture itself cannot place it: it says so and scores nothing.
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    cap = simulate_capture(still, sensor_preset("lcspc-sim"), fibonacci_hemisphere(2, 0.5), tmp_path / "cap",
                           settings=SimSettings(rays_per_zone=64), progress=False, scene=manifest["scene"])
    spec, why = capture_ground_truth(cap)
    assert spec is None and "offset by mesh_offset_m [0.1, 0.0, 0.02]" in why
    assert json.loads((cap / "scan.json").read_text())["scene"]["mesh_offset_m"] == [0.1, 0.0, 0.02]
