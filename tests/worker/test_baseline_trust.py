"""What the baselines say of a result that may be bad: a threshold that fits the capture's sensor, an implausible
carved hull called so, a calibrated threshold at an end of those tried; and the parts of the baselines whose edits
no other test noticed (multi-zone reprojection, the specks carving drops, --margin-mm, the floor's reach, the
occupancy surface's grid, the final metrics' point count)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from spadscan.cli import main as cli_main
from spadscan.protocol.errors import ConfigError
from spadscan.protocol.scenes import builtin_scene
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, Simulator
from spadscan.worker.baselines import common
from spadscan.worker.baselines.common import calibrate, points_mesh
from spadscan.worker.baselines.floor import check_given_floor
from spadscan.worker.baselines.reprojection import reproject_points
from spadscan.worker.ground_truth import GroundTruth


def _simulated(root, builtin: str, sensor: str, views: int):
    out = root / f"{builtin}-{sensor}"
    assert cli_main(["simulate", f"builtin:{builtin}", "--out", str(out), "--sensor", sensor, "--views", str(views),
                     "--no-progress"]) == 0
    return out


@pytest.fixture(scope="module")
def tmf_mug(tmp_path_factory):
    """The built-in mug (15 cm wide) seen by a TMF8820 from 48 views: at a threshold of 5 its carved hull was a metre
    wide (Chamfer 177 mm)."""
    return _simulated(tmp_path_factory.mktemp("tmf"), "mug", "tmf8820", 48)


@pytest.fixture(scope="module")
def lcspc_sphere(tmp_path_factory):
    return _simulated(tmp_path_factory.mktemp("lcspc"), "sphere", "lcspc-sim", 48)


def _baseline(capture, out, *options, method="space-carving") -> dict:
    assert cli_main(["baseline", method, str(capture), "--out", str(out), "--resolution", "48", *options]) == 0
    return json.loads((out / "report.json").read_text())


def test_a_tmf8820_capture_is_carved_at_its_sensors_threshold_not_a_metre_wide(tmf_mug, tmp_path, capsys):
    report = _baseline(tmf_mug, tmp_path / "carve", "--no-gt")
    hull = trimesh.load(tmp_path / "carve" / "mesh.ply")
    assert hull.extents.max() < 0.35, hull.extents  # the mug is 0.15 m wide; at 5 the hull spanned 1.05 m
    assert report["threshold"] == 20 and report["threshold_source"] == "the default for the tmf8820 sensor"
    assert report["implausible_hull"] is False and report["warnings"] == []
    assert "space-carving: threshold 20 (the default for the tmf8820 sensor)" in capsys.readouterr().out


def test_an_lcspc_capture_keeps_its_threshold_and_its_hull_passes(lcspc_sphere, tmp_path):
    report = _baseline(lcspc_sphere, tmp_path / "carve", "--no-gt")
    assert report["threshold"] == 5 and report["threshold_source"] == "the default for the lcspc-sim sensor"
    assert report["implausible_hull"] is False and report["hull_to_returns_span"] < 1.5


def test_an_implausible_hull_is_said_on_the_terminal_and_in_the_report(tmf_mug, tmp_path, capsys):
    """At a threshold of 5, noise passes for returns on a TMF8820 and the hull grows to a metre: the run must not pass
    that off as the method's result."""
    out = tmp_path / "carve"
    report = _baseline(tmf_mug, out, "--no-gt", "--threshold", "5")
    assert report["implausible_hull"] is True and report["hull_to_returns_span"] > 1.5
    said = [w for w in report["warnings"] if w.startswith("implausible hull")]
    assert len(said) == 1 and "times the" in said[0] and "--threshold" in said[0]
    seen = capsys.readouterr()
    assert [line for line in seen.err.splitlines() if "implausible hull" in line] == [
        f"spadscan baseline: warning: {said[0]}"]
    assert "IMPLAUSIBLE hull" in seen.out
    assert "implausible hull" in (out / "report.html").read_text()


def test_a_calibrated_threshold_at_the_end_of_those_tried_is_said(lcspc_sphere, tmp_path, monkeypatch, capsys):
    """The lowest threshold tried wins (the other finds no return): one below it, never tried, might do better."""
    monkeypatch.setattr(common, "CALIBRATION_THRESHOLDS", (4.0, 1e9))
    monkeypatch.setattr(common, "CALIBRATION_POINTS", 5_000)
    report = _baseline(lcspc_sphere, tmp_path / "carve", "--calibrate", "--points", "5000")
    assert report["threshold"] == 4.0 and report["calibration"]["edge"] == "lowest"
    said = [w for w in report["warnings"] if "the lowest of those tried" in w]
    assert len(said) == 1 and "below it" in said[0]
    assert f"spadscan baseline: warning: {said[0]}" in capsys.readouterr().err.splitlines()


def test_the_calibration_says_which_end_its_best_threshold_lies_at():
    sphere = builtin_scene("sphere")
    truth = GroundTruth(sphere)
    shrunk = sphere.copy().apply_scale(0.7)
    top = calibrate(lambda t: sphere if t == 3.0 else shrunk, truth, thresholds=(1.0, 2.0, 3.0), n_points=2_000)
    assert top.threshold == 3.0 and top.edge() == "highest" and "above it" in top.edge_note()
    middle = calibrate(lambda t: sphere if t == 2.0 else shrunk, truth, thresholds=(1.0, 2.0, 3.0), n_points=2_000)
    assert middle.threshold == 2.0 and middle.edge() is None and middle.edge_note() is None


def test_reprojection_puts_each_zones_point_along_its_own_zone():
    """A TMF8820 facing a wall 0.4 m away: each of its nine zones gives a point on the wall, in its own field of
    view (not all along the centre zone's axis)."""
    sensor = sensor_preset("tmf8820")
    wall = trimesh.creation.box([1.5, 1.5, 0.002]).apply_translation([0, 0, 0.401])
    poses = np.eye(4)[None]
    sim = Simulator(wall, sensor, SimSettings(rays_per_zone=512), seed=3)
    hists = sim.frames(poses).hists
    pts, view, zone, below = reproject_points(hists, poses, sim.sensor, threshold=20.0)
    assert sorted(zone.tolist()) == list(range(9)) and below == 0
    np.testing.assert_allclose(pts[:, 2], 0.4, atol=0.01)  # on the wall
    for p, z in zip(pts, zone):
        tan_x, tan_y = sensor.zones[z].tan_x, sensor.zones[z].tan_y
        assert tan_x[0] <= p[0] / p[2] <= tan_x[1] and tan_y[0] <= p[1] / p[2] <= tan_y[1], (z, p)


def test_carving_drops_specks_under_a_hundredth_of_the_largest_piece_and_keeps_the_rest(lcspc_sphere, tmp_path,
                                                                                      monkeypatch):
    """Carving leaves specks at the box's walls and beside sensors, where few views looked: pieces under 1 % of the
    largest go, a piece of 2.7 % stays."""
    import spadscan.worker.baselines.run as run
    from spadscan.worker.carving.space_carving import CarveResult

    occ = np.zeros((64,) * 3, bool)
    occ[5:25, 5:25, 5:25] = True  # 8000 voxels
    occ[40:46, 40:46, 40:46] = True  # 216: 2.7 %
    occ[55:58, 55:58, 55:58] = True  # 27: 0.34 %
    voxel = np.full(3, 0.005)

    def carved(*args, **kwargs):
        return CarveResult(occ, np.zeros(3), voxel, np.zeros(3), np.full(3, 0.32), kwargs["threshold"], 0.002)

    monkeypatch.setattr(run, "carve_scene", carved)
    report = run.run_baseline(lcspc_sphere, tmp_path / "carve", "space-carving", floor_z=None)
    pieces = sorted(len(p.vertices) for p in trimesh.load(tmp_path / "carve" / "mesh.ply").split(only_watertight=False))
    assert len(pieces) == 2, pieces
    assert report["hull_fraction"] == pytest.approx((8000 + 216) / 64 ** 3)


def test_margin_mm_is_the_range_left_uncarved_in_millimetres(lcspc_sphere, tmp_path):
    tight = _baseline(lcspc_sphere, tmp_path / "tight", "--no-gt", "--margin-mm", "0")
    loose = _baseline(lcspc_sphere, tmp_path / "loose", "--no-gt", "--margin-mm", "30")
    assert (tight["margin_mm"], loose["margin_mm"]) == (0.0, 30.0)
    grown = trimesh.load(tmp_path / "loose" / "mesh.ply").extents - trimesh.load(tmp_path / "tight" /
                                                                                 "mesh.ply").extents
    # 30 mm more on either side along x and y (z stands on the floor, and views from above)
    assert np.all((grown[:2] > 0.03) & (grown[:2] < 0.09)), grown


def test_a_floor_within_the_lowest_sensors_reach_is_accepted_though_the_highest_cannot_see_it():
    sensor = sensor_preset("lcspc-sim")
    poses = np.repeat(np.eye(4)[None], 2, axis=0)
    poses[:, 2, 3] = (0.1, 0.6)
    reach = sensor.max_range_m
    check_given_floor(0.1 - reach + 0.05, poses, sensor)  # beyond the higher sensor's reach, within the lower's
    check_given_floor(0.1 - reach, poses, sensor)  # at the edge of the histograms: a floor they can show
    with pytest.raises(ConfigError, match="beyond the histograms' range"):
        check_given_floor(0.1 - reach - 0.05, poses, sensor)


def test_the_occupancy_surface_splats_each_point_by_half_its_spacing():
    """Points 1 mm apart on a line: each is splatted by half the spacing (0.5 mm), so the surface is a rod about a
    spacing thick, a little less after the smoothing (0.72 mm). A grid of a third of the spacing gave 1.0 mm, a
    fifth 0.54 mm (splats that no longer touch: 47 pieces)."""
    line = np.zeros((50, 3))
    line[:, 0] = np.arange(50) * 1e-3
    mesh = points_mesh(line)
    assert 0.0006 < mesh.extents[1] < 0.0009 and 0.0006 < mesh.extents[2] < 0.0009, mesh.extents
    assert mesh.extents[0] == pytest.approx(0.049, abs=0.001)


def test_the_occupancy_surface_of_a_dense_long_cloud_stays_on_a_bounded_grid(monkeypatch):
    """Points 0.1 mm apart along 0.3 m: the grid is held to about 400 voxels across (not 3000), whatever the
    points' spacing, so that a dense cloud cannot take the memory of a 3000^3 grid."""
    shapes = []
    real = common.occupancy_mesh

    def spy(occ, *args, **kwargs):
        shapes.append(occ.shape)
        return real(occ, *args, **kwargs)

    monkeypatch.setattr(common, "occupancy_mesh", spy)
    line = np.zeros((3000, 3))
    line[:, 0] = np.arange(3000) * 1e-4
    assert points_mesh(line) is not None
    assert max(shapes[0]) <= 400 + 12, shapes


def test_the_final_metrics_use_the_points_asked_for(lcspc_sphere, tmp_path):
    report = _baseline(lcspc_sphere, tmp_path / "carve", "--points", "7000")
    assert report["n_points"] == report["queries"] == 7000
