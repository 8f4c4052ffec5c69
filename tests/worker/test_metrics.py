"""Mesh metrics: known distances between simple shapes, F-score around its threshold, normals, cropping, `spadscan eval`."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh

from spadscan.cli import main
from spadscan.protocol.errors import MeshError
from spadscan.protocol.mesh_io import load_mesh_spec
from spadscan.worker.metrics import MeshMetrics, crop_to_box, mesh_metrics, sample_surface, vertex_normal_error_deg

N = 40_000


def ball(radius=0.1, center=(0, 0, 0.1)):
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    return mesh.apply_translation(center)


def floor_mm(mesh, n):
    """Expected sample-to-sample distance between two independent samplings of the same surface (mm)."""
    return 0.5 * math.sqrt(mesh.area / n) * 1e3


@pytest.mark.slow
def test_identical_meshes_score_the_sampling_floor():
    mesh = ball()
    m = mesh_metrics(mesh, mesh.copy(), n_points=300_000)
    assert isinstance(m, MeshMetrics)
    floor = floor_mm(mesh, 300_000)  # ~0.33 mm
    assert 0.5 * floor < m.chamfer_mm < 1.3 * floor
    assert m.fscore_5mm == 1.0 and m.normal_error_deg < 3.0


def test_floor_shrinks_with_more_points():
    mesh = ball()
    coarse = mesh_metrics(mesh, mesh, n_points=5_000).chamfer_mm
    fine = mesh_metrics(mesh, mesh, n_points=80_000).chamfer_mm
    assert fine == pytest.approx(coarse / 4, rel=0.15)  # spacing ~ 1 / sqrt(n)


def test_sphere_two_millimetres_larger():
    # Sample spacing adds a little to the 2 mm gap (~0.1 mm at 100,000 points, ~0.03 mm at 300,000).
    m = mesh_metrics(ball(0.100), ball(0.102), n_points=100_000)
    assert m.chamfer_mm == pytest.approx(2.0, abs=0.15)
    assert m.accuracy_mm == pytest.approx(m.completeness_mm, rel=0.05)
    assert m.normal_error_deg < 2.0  # concentric spheres share their normals


def test_shifted_copy_of_a_sphere():
    # A sphere moved by d along x: the mean distance between the surfaces is E|d cos(theta)| = d / 2.
    shifted = ball().apply_translation([0.006, 0, 0])
    m = mesh_metrics(ball(), shifted, n_points=N)
    assert m.chamfer_mm == pytest.approx(3.0, abs=0.35)


def test_accuracy_and_completeness_are_not_swapped():
    full = ball()
    top_half = crop_to_box(full, [-1, -1, 0.1], [1, 1, 1])
    m = mesh_metrics(top_half, full, n_points=N)
    # Every point of the half lies on the whole (accuracy at the floor); half of the whole is far from the half.
    assert m.accuracy_mm < 1.5 * floor_mm(full, N)
    assert m.completeness_mm > 20
    assert m.precision == 1.0 and 0.45 < m.recall < 0.6


@pytest.mark.parametrize("gap_mm,expect", [(3.5, 1.0), (4.5, 1.0), (5.5, 0.0), (8.0, 0.0)])
def test_fscore_switches_at_five_millimetres(gap_mm, expect):
    m = mesh_metrics(ball(0.1), ball(0.1 + gap_mm * 1e-3), n_points=N)
    assert m.fscore_5mm == pytest.approx(expect, abs=0.02)


def test_fscore_threshold_is_a_parameter():
    a, b = ball(0.1), ball(0.107)
    assert mesh_metrics(a, b, n_points=N).fscore_5mm < 0.01
    m = mesh_metrics(a, b, n_points=N, fscore_threshold_m=0.008)
    assert m.fscore_5mm > 0.99 and m.fscore_threshold_mm == pytest.approx(8.0)


def test_normal_error_of_a_tilted_plate_and_flipped_orientation():
    plate = trimesh.creation.box([0.2, 0.2, 0.002])
    tilt = trimesh.transformations.rotation_matrix(math.radians(10), [1, 0, 0])
    tilted = plate.copy().apply_transform(tilt)
    base = mesh_metrics(plate, plate.copy(), n_points=N).normal_error_deg  # samples near edges: ~1.4 deg
    assert base < 3
    assert mesh_metrics(plate, tilted, n_points=N).normal_error_deg - base == pytest.approx(10.0, abs=1.0)
    flipped = plate.copy()
    flipped.invert()
    assert mesh_metrics(plate, flipped, n_points=N).normal_error_deg == pytest.approx(base, abs=0.5)  # orientation ignored


def fine_copy(mesh, edge_m=0.004):
    """The same surface in small triangles: a perfect reconstruction of `mesh`."""
    fine = mesh.subdivide_to_size(edge_m, max_iter=20)
    return trimesh.Trimesh(fine.vertices, fine.faces)


@pytest.mark.parametrize("scene,mean_below", [("pyramid", 3.0), ("tall-block", 3.0), ("sphere", 2.0)])
def test_per_vertex_normal_error_of_a_perfect_mesh_is_near_zero(scene, mean_below):
    # A flat-faced ground truth shares its corners between faces meeting at 45-90 deg: its own vertex normals,
    # interpolated, would tilt the "true" normal across every face (a perfect pyramid scored ~40 deg).
    gt = load_mesh_spec(f"builtin:{scene}")[0]
    err = vertex_normal_error_deg(fine_copy(gt), gt, n_gt=50_000)
    assert err.mean() < mean_below and np.median(err) < 2.0


def test_per_vertex_normal_error_sees_a_turned_mesh():
    gt = load_mesh_spec("builtin:tall-block")[0]
    turned = fine_copy(gt).apply_transform(trimesh.transformations.rotation_matrix(math.radians(20), [0, 0, 1]))
    side = np.abs(turned.vertex_normals[:, 2]) < 0.1  # the four walls, now 20 deg off the ground truth's
    err = vertex_normal_error_deg(turned, gt, n_gt=50_000)
    assert np.median(err[side]) == pytest.approx(20.0, abs=1.0)


def test_same_seed_same_numbers_other_seed_close():
    a, b = ball(), ball(0.103)
    m1, m2 = mesh_metrics(a, b, n_points=N, seed=3), mesh_metrics(a, b, n_points=N, seed=3)
    m3 = mesh_metrics(a, b, n_points=N, seed=4)
    assert m1 == m2 and m1 != m3
    assert m3.chamfer_mm == pytest.approx(m1.chamfer_mm, abs=0.05)


def test_sampling_is_uniform_by_area():
    # Two faces, one with 3x the area of the other: 3x the samples.
    mesh = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [2, 3, 0], [5, 0, 0]],
                           [[0, 1, 2], [3, 5, 4]], process=False)
    pts, nrm = sample_surface(mesh, 40_000, np.random.default_rng(0))
    assert np.mean(pts[:, 0] >= 2) == pytest.approx(9 / 10, abs=0.01)
    assert np.all(pts[:, 0] >= 0) and np.allclose(pts[:, 2], 0) and np.allclose(np.abs(nrm[:, 2]), 1)
    inside_first = pts[pts[:, 0] < 1.5]
    assert np.all(inside_first[:, 0] + inside_first[:, 1] <= 1 + 1e-12)  # inside the triangle, not the square


@pytest.mark.parametrize("kwargs,match", [({"n_points": 0}, "points"), ({"seed": -1}, "seed"),
                                          ({"fscore_threshold_m": 0.0}, "threshold"),
                                          ({"fscore_threshold_m": float("nan")}, "threshold"),
                                          ({"deadline": float("nan")}, "deadline")])
def test_bad_parameters(kwargs, match):
    with pytest.raises(MeshError, match=match):
        mesh_metrics(ball(), ball(), **kwargs)


def test_bad_meshes():
    nan = ball()
    nan.vertices[0, 0] = np.nan
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)
    for bad, match in ((trimesh.Trimesh(), "no triangles"), (nan, "non-finite"), (flat, "zero surface area"),
                       ("mesh.obj", "trimesh")):
        with pytest.raises(MeshError, match=match):
            mesh_metrics(bad, ball())
        with pytest.raises(MeshError, match="ground truth"):
            mesh_metrics(ball(), bad)


def test_crop_to_box():
    mesh = ball()
    top = crop_to_box(mesh, [-1, -1, 0.15], [1, 1, 1])
    assert top.triangles_center[:, 2].min() >= 0.15 and top.bounds[1, 2] == pytest.approx(0.2)
    assert len(top.vertices) < len(mesh.vertices)  # unreferenced vertices dropped
    with pytest.raises(MeshError, match="no triangle"):
        crop_to_box(mesh, [1, 1, 1], [2, 2, 2])
    with pytest.raises(MeshError, match="below max"):
        crop_to_box(mesh, [0, 0, 0.2], [1, 1, 0.1])
    with pytest.raises(MeshError, match="3-vectors"):
        crop_to_box(mesh, [0, 0], [1, 1, 1])


# ---- spadscan eval ------------------------------------------------------------------------------------------------------
def test_eval_detects_millimetre_stl_and_prints_json(tmp_path, capsys):
    gt = ball()
    gt.export(tmp_path / "gt.obj")
    ball(100.0, (0, 0, 100.0)).export(tmp_path / "recon.stl")  # the same ball, in millimetres
    rc = main(["eval", str(tmp_path / "recon.stl"), "--gt", str(tmp_path / "gt.obj"), "--json", "--points", str(N)])
    assert rc == 0
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert out["chamfer_mm"] < 1.5 * floor_mm(gt, N) and out["fscore_5mm"] == 1.0 and out["n_points"] == N
    assert (out["mesh_units"], out["gt_units"]) == ("mm", "m")
    assert out["ground_truth"] == out["gt"] and out["ground_truth_cut_above_z_m"] is None  # as in the reports
    assert captured.err == f"{tmp_path / 'recon.stl'}: read as millimetres (over 5 m across as metres; --units m " \
                           f"to read it as metres)\n"
    assert {"accuracy_mm", "completeness_mm", "normal_error_deg", "mesh", "gt"} <= set(out)


def test_the_f_score_key_names_its_threshold(tmp_path, capsys):
    ball().export(tmp_path / "gt.ply")
    base = ["eval", str(tmp_path / "gt.ply"), "--gt", str(tmp_path / "gt.ply"), "--json", "--points", "2000"]
    assert main([*base, "--threshold-mm", "10"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["fscore_10mm"] > 0.9 and "fscore_5mm" not in out and out["fscore_threshold_mm"] == 10.0
    assert main(base) == 0
    assert "fscore_5mm" in json.loads(capsys.readouterr().out)
    assert main([*base, "--threshold-mm", "0"]) == 1
    assert capsys.readouterr().err == "spadscan: error: --threshold-mm 0 must be a distance in (0, 10000) mm\n"


def test_eval_table_and_builtin_scenes(capsys):
    assert main(["eval", "builtin:cup", "--gt", "builtin:cup", "--points", "5000", "--seed", "2"]) == 0
    out = capsys.readouterr().out
    for key in ("Chamfer", "accuracy", "completeness", "F-score @5 mm", "normal error", "mm", "seed 2"):
        assert key in out
    chamfer = float(next(line for line in out.splitlines() if line.startswith("Chamfer")).split()[1])
    assert 0 < chamfer < 3


def test_eval_scores_the_object_above_a_table_in_the_ground_truth_unless_told_otherwise(tmp_path, capsys):
    plate = trimesh.creation.box([2.0, 2.0, 0.02]).apply_translation([0, 0, -0.01])
    scene = trimesh.util.concatenate([plate, ball()])
    scene.export(tmp_path / "gt.ply")
    ball().export(tmp_path / "recon.ply")
    args = ["eval", str(tmp_path / "recon.ply"), "--gt", str(tmp_path / "gt.ply"), "--points", str(N)]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "scored" in out and "the object above z = 0.0050 m" in out and "table top + 5 mm" in out
    chamfer = float(next(line for line in out.splitlines() if line.startswith("Chamfer")).split()[1])
    assert chamfer < 1.5 * floor_mm(ball(), N)
    assert main(args + ["--json"]) == 0
    assert json.loads(capsys.readouterr().out)["cut_above_z_m"] == pytest.approx(0.005)
    assert main(args + ["--json", "--keep-table"]) == 0
    whole = json.loads(capsys.readouterr().out)
    assert whole["completeness_mm"] > 100 and whole["cut_above_z_m"] is None  # the table dominates
    assert main(args + ["--json", "--box", "-0.2", "-0.2", "0.001", "0.2", "0.2", "0.3"]) == 0
    boxed = json.loads(capsys.readouterr().out)
    assert boxed["chamfer_mm"] < 1.5 * floor_mm(ball(), N) and boxed["cut_above_z_m"] is None


@pytest.mark.parametrize("content,name", [(None, "missing.obj"), ("not a mesh\n", "bad.obj"), (b"", "empty.stl")])
def test_eval_bad_files_are_one_line_errors(tmp_path, capsys, content, name):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
    assert main(["eval", str(path), "--gt", "builtin:sphere"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("spadscan: error:") and name in err and err.count("\n") == 1


def test_eval_bad_options_are_one_line_errors(capsys):
    assert main(["eval", "builtin:sphere", "--gt", "builtin:teapot"]) == 1
    assert "teapot" in capsys.readouterr().err
    assert main(["eval", "builtin:sphere", "--gt", "builtin:sphere", "--points", "-5"]) == 1
    assert capsys.readouterr().err.count("\n") == 1


@pytest.mark.parametrize("case", ["small sphere inside a large one", "shifted 3 cm", "box beside a sphere", "close",
                                  "40 cm apart"])
def test_nearest_samples_are_exactly_the_kd_trees(case):
    from scipy.spatial import cKDTree

    from spadscan.worker.nearest import nearest_samples

    a, b = {"small sphere inside a large one": (ball(0.02), ball(0.05)),
            "shifted 3 cm": (ball(0.05), ball(0.05, (0.03, 0, 0.1))),
            "box beside a sphere": (trimesh.creation.box((0.05, 0.02, 0.08)), ball(0.05, (0.1, 0, 0))),
            "close": (ball(0.05), ball(0.051)),
            "40 cm apart": (ball(0.05), ball(0.05, (0.5, 0, 0)))}[case]
    rng = np.random.default_rng(1)
    q, _ = sample_surface(a, 12_000, rng)
    d, _ = sample_surface(b, 9_000, rng)
    dist, idx = nearest_samples(q, d, spacing_m=math.sqrt(b.area / len(d)))
    ref, ref_idx = cKDTree(d).query(q)
    np.testing.assert_allclose(dist, ref, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(q - d[idx], axis=1), dist, rtol=0, atol=1e-15)
    assert np.mean(idx == ref_idx) > 0.999  # exact ties aside, the very same samples


def test_far_queries_skip_the_kd_tree():
    from spadscan.worker.nearest import _maybe_near, split_patches

    rng = np.random.default_rng(2)
    big, _ = sample_surface(ball(0.05), 20_000, rng)
    small, _ = sample_surface(ball(0.02), 20_000, rng)
    patches = split_patches(big)
    assert not _maybe_near(small, 0.005, patches).any(), "3 cm from every sample: none is near"
    assert _maybe_near(big, 0.005, patches).all()


def test_a_small_sphere_inside_a_large_one_is_its_gap_away():
    m = mesh_metrics(ball(0.02), ball(0.05), n_points=N)
    assert m.accuracy_mm == pytest.approx(30.0, abs=0.1) and m.completeness_mm == pytest.approx(30.0, abs=0.1)
    assert m.fscore_5mm == 0.0


def fragment():
    """A 1 mm triangle 25 cm from `ball()`s: its samples are far smaller than their distance to a ball's, so every
    patch of them crowds every query block."""
    return trimesh.Trimesh([[0.3, 0, 0.1], [0.301, 0, 0.1], [0.3, 0.001, 0.1]], [[0, 1, 2]], process=False)


@pytest.mark.parametrize("case", ["small sphere inside a large one", "sphere against a far fragment"])
def test_a_sample_index_answers_queries_in_parts_as_at_once(case):
    """The same distances and samples whether queries come at once or in parts (metrics measured in chunks until a
    deadline): the tree's, the patch search's and, for the fragment, the crowded blocks' answers."""
    from spadscan.worker.nearest import SampleIndex, nearest_samples

    rng = np.random.default_rng(3)
    query_mesh, data_mesh, n_data = {"small sphere inside a large one": (ball(0.02), ball(0.05), 9_000),
                                     "sphere against a far fragment": (ball(0.05), fragment(), 20_000)}[case]
    q, _ = sample_surface(query_mesh, 12_000, rng)  # far from the data: the patch search as well as the tree
    d, _ = sample_surface(data_mesh, n_data, rng)
    whole = nearest_samples(q, d, spacing_m=0.001)
    index = SampleIndex(d, spacing_m=0.001)
    parts = [index.query(q[a:a + 5_000]) for a in range(0, len(q), 5_000)]
    for k in range(2):
        np.testing.assert_array_equal(np.concatenate([p[k] for p in parts]), whole[k])


def test_a_sample_index_queried_in_parts_builds_its_trees_and_patches_once(monkeypatch):
    """Queries in parts (metrics measured in chunks) search the same KD-trees and patch bounds: built once, not once
    a part (that made chunked metrics half again as slow as in one shot). Far queries into a fragment use them all:
    the patch search, the centroids' tree and, for the crowded blocks, the samples' tree."""
    import spadscan.worker.nearest as nearest

    built = {"trees": 0, "bounds": 0}

    def counted(name, make):
        def counting(*args, **kwargs):
            built[name] += 1
            return make(*args, **kwargs)
        return counting

    monkeypatch.setattr(nearest, "cKDTree", counted("trees", nearest.cKDTree))
    monkeypatch.setattr(nearest, "_patch_bounds", counted("bounds", nearest._patch_bounds))
    rng = np.random.default_rng(5)
    q, _ = sample_surface(ball(0.05), 20_000, rng)
    d, _ = sample_surface(fragment(), 20_000, rng)
    index = nearest.SampleIndex(d)
    for a in range(0, len(q), 5_000):
        index.query(q[a:a + 5_000])
    assert built == {"trees": 2, "bounds": 1}, "the samples' tree and the centroids' tree, the bounds once"


def test_a_small_fragment_far_from_the_truth_gets_exact_distances_from_both_sides():
    """Samples far smaller than their distance to the queries (a 1 mm fragment 25 cm from the ground truth): every
    patch is a candidate for every query block, which the KD-tree of the samples answers instead; both directions
    exact against a plain search."""
    from scipy.spatial import cKDTree

    from spadscan.worker.nearest import CROWDED_PATCHES, LEAF, nearest_samples

    rng = np.random.default_rng(4)
    f, _ = sample_surface(fragment(), 40_000, rng)
    g, _ = sample_surface(ball(0.05), 40_000, rng)
    assert len(f) // LEAF > CROWDED_PATCHES, "enough patches for a query block to be crowded by them"
    for q, d in ((g, f), (f, g)):
        dist, idx = nearest_samples(q, d)
        want, _ = cKDTree(d).query(q)
        np.testing.assert_allclose(dist, want, rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(q - d[idx], axis=1), want, rtol=0, atol=1e-12)


class StepClock:
    """A clock that only the measured samples move: `per_query` seconds for each query answered."""

    def __init__(self, per_query: float):
        self.t, self.per_query = 0.0, per_query

    def __call__(self) -> float:
        return self.t


def timed_index(clock: StepClock):
    """metrics.SampleIndex whose queries advance `clock`."""
    from spadscan.worker.nearest import SampleIndex

    class Timed(SampleIndex):
        def query(self, queries):
            clock.t += clock.per_query * len(queries)
            return super().query(queries)

    return Timed


@pytest.mark.parametrize("case", ["overlapping spheres", "a fragment far from a sphere"])
def test_metrics_with_a_far_deadline_are_the_metrics_without_one(monkeypatch, case):
    """Every figure identical, measured in chunks or at once; the fragment's queries take the patch search and the
    crowded blocks' KD-tree."""
    import spadscan.worker.metrics as metrics

    clock = StepClock(1e-6)
    monkeypatch.setattr(metrics, "SampleIndex", timed_index(clock))
    a, b = {"overlapping spheres": (ball(0.05), ball(0.05, (0.02, 0, 0.1))),
            "a fragment far from a sphere": (fragment(), ball(0.05))}[case]
    whole = mesh_metrics(a, b, n_points=N)
    chunked = mesh_metrics(a, b, n_points=N, deadline=1e9, clock=clock)
    assert clock.t > 0, "the chunks were timed"
    assert chunked == whole and chunked.queries == N


def test_a_deadline_stops_the_metrics_at_the_chunk_that_would_pass_it(monkeypatch):
    """Chunks of 500, 1,000, 2,000, 4,000 and 8,000 samples at 1 ms a query and side take 1, 2, 4, 8 and 16 s:
    with a deadline at 45 s the sixth (32 s) would end at 63 s, so the metrics rest on the first 15,500 samples of
    each mesh."""
    import spadscan.worker.metrics as metrics
    from spadscan.worker.metrics import FIRST_QUERIES

    clock = StepClock(1e-3)
    monkeypatch.setattr(metrics, "SampleIndex", timed_index(clock))
    a, b = ball(0.05), ball(0.052)
    cut = mesh_metrics(a, b, n_points=N, deadline=45.0, clock=clock)
    assert FIRST_QUERIES == 500 and cut.queries == 15_500 and cut.n_points == N
    assert clock.t == pytest.approx(31.0)
    whole = mesh_metrics(a, b, n_points=N)
    assert cut.chamfer_mm == pytest.approx(whole.chamfer_mm, rel=0.02), "the first samples drawn: an unbiased share"
    slow = StepClock(0.01)  # queries as slow as those at the centre of a sphere ten times the ground truth's size
    monkeypatch.setattr(metrics, "SampleIndex", timed_index(slow))
    late = mesh_metrics(a, b, n_points=N, deadline=-1.0, clock=slow)
    assert late.queries == FIRST_QUERIES, "a deadline already past still measures the first chunk"
    assert slow.t == pytest.approx(10.0), "and that chunk alone: 10 s past the deadline, not minutes"
