"""Returns the mesh does not account for: a part of the object lost whole says so.

A thin upright rod that carving cut away left a mesh of next to nothing that was one piece, seen by many views and
within the photon noise where its few photons were: no check said a word. Its first returns came from where the mesh
has no surface, which is what `lost_returns` counts."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import trimesh

from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.schedules import fibonacci_hemisphere, look_at
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.sim_table import SimTable
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker.end_of_run import RunFacts, lost_warning, warnings
from spadscan.protocol.scenes import builtin_scene
from spadscan.worker import lost_returns as lost_module
from spadscan.worker.lost_returns import (LEAK_SHARE, LOST_MIN, LOST_SHARE_MEASURED, LOST_SHARE_SIMULATED,
                                          LOST_TOLERANCE_M, LostReturns, in_sphere_reach, leaked, lost_returns,
                                          nearest_surface, table_range)

BOX = (0.07, 0.05, 0.09)
"""The scene's box (metres), standing on z = 0."""


def box(height: float = BOX[2]) -> trimesh.Trimesh:
    """The box, or its lowest `height` metres."""
    return trimesh.creation.box(extents=(BOX[0], BOX[1], height)).apply_translation([0.0, 0.0, 0.5 * height])


@pytest.fixture(scope="module")
def box_capture(tmp_path_factory):
    """(counts (V, 1, bins), poses, sensor): 24 simulated views of the box from 0.3 m, the dataset's simulated
    sensor, no table."""
    path = tmp_path_factory.mktemp("lost") / "box"
    poses = fibonacci_hemisphere(24, 0.3, target=(0, 0, 0.045), min_elevation_deg=15)
    simulate_capture(box(), sensor_preset("lcspc-sim"), poses, path, settings=SimSettings(rays_per_zone=256),
                     progress=False)
    capture = CaptureReader(path).load()
    return capture.by_pose().counts, capture.poses[capture.by_pose().first], capture.sensor


@pytest.fixture(scope="module")
def table_capture(tmp_path_factory):
    """The same for the 9-zone TMF8820 with the box on a black table at z = 0: the outer zones see the table."""
    path = tmp_path_factory.mktemp("lost") / "box-on-table"
    poses = fibonacci_hemisphere(24, 0.3, target=(0, 0, 0.045), min_elevation_deg=30)
    simulate_capture(box(), sensor_preset("tmf8820"), poses, path, settings=SimSettings(rays_per_zone=64),
                     table=SimTable(0.0), progress=False)
    capture = CaptureReader(path).load()
    return capture.by_pose().counts, capture.poses[capture.by_pose().first], capture.sensor, path


def test_the_table_s_nearest_point_in_a_cone():
    """Straight down from 0.5 m the table is 0.5 m away; tilted 45 degrees, its nearest point in the cone is along
    the cone's lowest edge; looking up, the zone never meets it."""
    sensor = sensor_preset("lcspc-sim")
    half = sensor.zones[0].half_angle_rad
    down = look_at([0, 0, 0.5], [0, 0, 0])
    slant = look_at([0, 0, 0.5], [0.5, 0, 0])
    up = look_at([0, 0, 0.5], [0, 0, 1.0])
    got = table_range(np.array([0.0, 0.0, 1.0]), 0.0, np.stack([down, slant, up]), sensor)[:, 0]
    assert got[0] == pytest.approx(0.5)
    assert got[1] == pytest.approx(0.5 / math.cos(math.radians(45.0) - half), rel=1e-3)
    assert got[2] == math.inf


def test_the_table_straight_down_in_a_rect_zone():
    """A 9-zone sensor looking 2 degrees off straight down: its middle zone holds the plane's nearest point, at the
    sensor's height; a corner zone's nearest point is along its steepest edge, farther."""
    sensor = sensor_preset("tmf8820")
    tilt = math.radians(2.0)
    pose = look_at([0, 0, 0.5], [0.5 * math.tan(tilt), 0, 0])
    got = table_range(np.array([0.0, 0.0, 1.0]), 0.0, pose[None], sensor)[0]
    middle = [i for i, zone in enumerate(sensor.zones) if zone.holds(np.array([0.0, 0.0, 1.0]))]
    assert got[middle] == pytest.approx(0.5)
    assert np.all(np.delete(got, middle) > 0.5)


def test_the_nearest_surface_point_in_each_zone():
    """Of points in front of a 9-zone sensor, each zone's nearest in its own field of view; none where a zone holds
    no point."""
    sensor = sensor_preset("tmf8820")
    pose = look_at([0, 0, 0], [0, 0, 1.0])
    centre = np.array([[0.0, 0.0, 0.4], [0.0, 0.0, 0.3]])  # both in the middle zone
    near = nearest_surface(centre, pose[None], sensor)[0]
    middle = [i for i, zone in enumerate(sensor.zones) if zone.holds(np.array([0.0, 0.0, 1.0]))]
    assert near[middle] == pytest.approx(0.3)
    assert np.all(np.isinf(np.delete(near, middle)))


def test_a_return_counts_only_where_it_can_have_come_from_the_scene_s_sphere():
    """A return at the range of a 10 cm ball ahead is judged; one far beyond it, or from a zone looking away from
    it, is not (the room behind, which no fit models)."""
    sensor = sensor_preset("lcspc-sim")
    ahead = look_at([0, 0, 0.5], [0, 0, 0])
    away = look_at([0, 0, 0.5], [0, 0, 1.0])
    ranges = np.array([[0.45], [0.9], [0.45]])
    got = in_sphere_reach(ranges, np.stack([ahead, ahead, away]), sensor, np.zeros(3), 0.1)[:, 0]
    assert got.tolist() == [True, False, False]
    # A small ball inside the cone but off its axis (9 degrees of its 15): judged.
    aside = in_sphere_reach(np.array([[0.5]]), ahead[None], sensor, np.array([0.08, 0.0, 0.0]), 0.02)
    assert aside[0, 0]


def test_the_right_mesh_accounts_for_every_return_and_a_lost_part_does_not(box_capture):
    counts, poses, sensor = box_capture
    whole = lost_returns(counts, poses, sensor, box(), np.array([0, 0, 0.045]), 0.1)
    assert whole.returns == 24 and whole.lost == 0 and not whole.says
    # The box's top two thirds lost: the views from above saw them first.
    stump = lost_returns(counts, poses, sensor, box(0.03), np.array([0, 0, 0.045]), 0.1)
    assert stump.lost >= LOST_MIN and stump.share > LOST_SHARE_SIMULATED and stump.says
    assert stump.heights_m is not None and stump.heights_m[1] > 0.03
    # Its top 2 cm lower: within the tolerance the bulk behind the nearest point allows, nothing is lost.
    assert lost_returns(counts, poses, sensor, box(BOX[2] - 0.02), np.array([0, 0, 0.045]), 0.1).lost == 0
    # Nothing left at all: every return is lost.
    empty = lost_returns(counts, poses, sensor, trimesh.Trimesh(), np.array([0, 0, 0.045]), 0.1)
    assert empty.lost == empty.returns == 24


def test_a_real_capture_is_held_to_its_own_limit(box_capture):
    """A measured capture's sensor leaves returns no model accounts for: its limit is LOST_SHARE_MEASURED. The box
    cut to half its height loses a share between the two limits: said of a simulated capture, not of a real one."""
    counts, poses, sensor = box_capture
    args = (counts, poses, sensor, box(0.045), np.array([0, 0, 0.045]), 0.1)
    simulated, measured = lost_returns(*args), lost_returns(*args, measured=True)
    assert simulated.lost == measured.lost and LOST_SHARE_SIMULATED < measured.share <= LOST_SHARE_MEASURED
    assert simulated.says and not measured.says and measured.limit == LOST_SHARE_MEASURED


def test_histograms_without_data_are_not_judged_and_a_large_capture_is_read_on_spread_views(box_capture):
    """Views whose histograms hold no data are left out, and of more views than `max_views` that many are judged."""
    counts, poses, sensor = box_capture
    usable = np.ones(counts.shape[:2], bool)
    usable[:6] = False
    args = (counts, poses, sensor, trimesh.Trimesh(), np.array([0, 0, 0.045]), 0.1)
    assert lost_returns(*args, usable=usable).returns == 18
    assert lost_returns(*args, usable=usable, max_views=12).returns == 12


def test_a_part_too_small_to_be_drawn_keeps_its_corners():
    """The points the zones are tested on hold the mesh's vertices as well as the draw over its area: a sliver
    a billionth of the area keeps its place."""
    big = [[-1, -1, 0], [1, -1, 0], [0, 1, 0]]
    sliver = [[5, 5, 1], [5.0001, 5, 1], [5, 5.0001, 1]]
    mesh = trimesh.Trimesh(vertices=np.array(big + sliver, float), faces=[[0, 1, 2], [3, 4, 5]])
    points = lost_module._surface_points(mesh)
    assert np.any(np.all(np.isclose(points, sliver[0]), axis=1))


def test_the_table_accounts_for_the_outer_zones_returns(table_capture):
    """On a table the outer zones' first returns are the table's: with its plane they are accounted for, without it
    they would pass for lost returns, at the table's height."""
    counts, poses, sensor, _ = table_capture
    table = (np.array([0.0, 0.0, 1.0]), 0.0)
    with_table = lost_returns(counts, poses, sensor, box(), np.array([0, 0, 0.045]), 0.15, table)
    assert with_table.returns > 24 * 4 and with_table.share <= LOST_SHARE_SIMULATED, with_table
    without = lost_returns(counts, poses, sensor, box(), np.array([0, 0, 0.045]), 0.15)
    assert without.lost >= with_table.lost + 10 and abs(without.heights_m[1]) < 0.01, without  # the table's


def test_a_weak_return_at_a_kept_return_s_range_is_its_light_in_the_wrong_zone():
    """One view of three zones: zone 0's bright return is accounted for; zone 1's, at its range and under LEAK_SHARE
    of its peak, is its light; zone 2's, as weak but 10 cm nearer, is not."""
    ranges = np.array([[0.30, 0.31, 0.20]])
    peak = np.array([[1000.0, 0.5 * LEAK_SHARE * 1000.0, 0.5 * LEAK_SHARE * 1000.0]])
    lost = np.array([[False, True, True]])
    assert leaked(lost, ~lost, ranges, peak).tolist() == [[False, True, False]]
    # Not light of a return that is itself lost, nor of one as weak as it.
    assert not leaked(lost, np.zeros_like(lost), ranges, peak).any()
    assert not leaked(lost, ~lost, ranges, np.array([[1000.0, 900.0, 900.0]])).any()


def test_a_bright_9_zone_capture_s_crosstalk_is_not_a_lost_part(tmp_path, monkeypatch):
    """The duck at three times the laser power seen by the TMF8820 without a table: the true mesh accounts for every
    return; read without the leak rule, the residue of the crosstalk's unmixing in the zones beside the duck would
    pass for lost returns."""
    mesh = builtin_scene("duck")
    middle = float(mesh.bounds[1, 2]) / 2
    poses = fibonacci_hemisphere(32, 0.35, target=(0, 0, middle), min_elevation_deg=20)
    simulate_capture(mesh, sensor_preset("tmf8820"), poses, tmp_path / "duck",
                     settings=SimSettings(rays_per_zone=64, power=3.0), progress=False)
    capture = CaptureReader(tmp_path / "duck").load()
    counts, poses = capture.by_pose().counts, capture.poses[capture.by_pose().first]
    centre = np.array([0.0, 0.0, middle])
    kept = lost_returns(counts, poses, capture.sensor, mesh, centre, 0.2)
    monkeypatch.setattr(lost_module, "LEAK_SHARE", 0.0)
    unread = lost_returns(counts, poses, capture.sensor, mesh, centre, 0.2)
    assert unread.lost >= 10 and kept.lost <= unread.lost // 4 and not kept.says, (kept, unread)


def test_the_warning_says_how_much_where_and_what_to_do():
    lost = LostReturns(returns=241, lost=213, heights_m=(0.0, 0.08))
    line = lost_warning(lost)
    assert line.startswith("88.4 % of the first returns that can have come from the object (213 of 241) come from "
                           "where the mesh has no surface, mostly at heights 0.00 to 0.08 m"), line
    assert f"over {LOST_TOLERANCE_M * 1e3:.0f} mm nearer" in line and "preview.png" in line
    assert line in warnings(RunFacts(stopped_by="converged", steps=100, model_converged=True,
                                     data_terms=[1.0] * 100, lost=lost, measured=False))
    assert lost_warning(LostReturns(returns=10, lost=2)) is None  # 20 %, but too few to be a pattern
    assert lost_warning(LostReturns(returns=241, lost=16)) is None  # 6.6 %: within the limit
    assert lost_warning(None) is None


@pytest.mark.usefixtures("one_thread")
def test_reconstruct_records_the_lost_returns_and_warns(tmp_path, monkeypatch):
    """The run's wiring: report.json holds the count, and a mesh that lost the box's top says so on the terminal
    and in the report."""
    from spadscan.worker.recon.fast.model import FastModel
    from spadscan.worker.reconstruct import reconstruct_capture

    poses = fibonacci_hemisphere(24, 0.3, target=(0, 0, 0.045), min_elevation_deg=15)
    simulate_capture(box(), sensor_preset("lcspc-sim"), poses, tmp_path / "cap",
                     settings=SimSettings(rays_per_zone=256), progress=False)
    monkeypatch.setattr(FastModel, "extract_mesh", lambda self, resolution=None, averaged=True: box(0.03))
    said = []
    report = reconstruct_capture(tmp_path / "cap", tmp_path / "out", steps=5, progress=False, device="cpu",
                                 threads=1, log=said.append, overrides={"mesh_resolution": 48, "early_stop": False})
    record = report["lost_returns"]
    assert record["returns"] == 24 and record["lost"] >= LOST_MIN and record["limit"] == LOST_SHARE_SIMULATED
    lines = [w for w in report["warnings"] if "come from where the mesh has no surface" in w]
    assert len(lines) == 1 and any(lines[0] in line for line in said), said


@pytest.mark.usefixtures("one_thread")
def test_reconstruct_holds_the_returns_against_the_table_it_fitted(table_capture, tmp_path, monkeypatch):
    """The run's wiring on a table: the table the fit ended with accounts for the outer zones' returns (held against
    the mesh alone, the table's returns read as lost), and a capture marked measured is held to its own limit."""
    from spadscan.worker.recon.fast.model import FastModel
    from spadscan.worker.reconstruct import reconstruct_capture

    counts, poses, sensor, path = table_capture
    monkeypatch.setattr(FastModel, "extract_mesh", lambda self, resolution=None, averaged=True: box())
    small = {"mesh_resolution": 48, "early_stop": False}
    report = reconstruct_capture(path, tmp_path / "out", steps=5, progress=False, device="cpu", threads=1,
                                 overrides=small)
    alone = lost_returns(counts, poses, sensor, box(), np.array([0, 0, 0.045]), 0.15)
    record = report["lost_returns"]
    assert record["returns"] > 24 * 4 and record["lost"] < LOST_MIN <= alone.lost - 5, (record, alone)
    real = tmp_path / "real"
    shutil.copytree(path, real)
    manifest = json.loads((real / "scan.json").read_text())
    manifest["scene"]["real"] = True
    (real / "scan.json").write_text(json.dumps(manifest))
    measured = reconstruct_capture(real, tmp_path / "real-out", steps=5, progress=False, device="cpu", threads=1,
                                   overrides=small)
    assert measured["lost_returns"]["limit"] == LOST_SHARE_MEASURED
