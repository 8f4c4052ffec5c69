"""Reprojection's first returns on the TMF8820, whose pulse has a ~40-bin tail: a return lies where the surface is,
never in front of the sensor; and histograms no sensor could have produced stay out of reprojection and out of the
crosstalk unmixing of the other zones of their view (in reprojection and in carving's limits)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import trimesh

from spadscan.cli import main as cli_main
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.plausibility import implausible
from spadscan.protocol.scenes import builtin_scene
from spadscan.worker.baselines import reprojection as reproj
from spadscan.worker.baselines.reprojection import reproject_points, reprojection
from spadscan.worker.carving import returns
from spadscan.worker.carving.returns import FirstReturns, first_returns, photon_signal
from spadscan.worker.carving.space_carving import carve_limits

COUNTER = 2**24 - 1  # the TMF8820's 24-bit counter
CORRUPT = {(3, 4): "saturated", (5, 4): "over the counter"}
"""(view, zone) of the histograms `_corrupt` spoils: the middle zone, whose return is the strongest of its view."""


@pytest.fixture(scope="module")
def tmf_sphere(tmp_path_factory):
    """The built-in sphere, 24 simulated TMF8820 views from 20 degrees up (a capture folder)."""
    path = tmp_path_factory.mktemp("tmf") / "sphere"
    assert cli_main(["simulate", "builtin:sphere", "--out", str(path), "--sensor", "tmf8820", "--views", "24",
                     "--min-elevation", "20", "--seed", "0", "--no-progress"]) == 0
    return path


def _load(path):
    data = CaptureReader(path).load()
    return data.hists, data.poses, data.sensor


def _corrupt(hists: np.ndarray) -> np.ndarray:
    """The histograms with view 3's middle zone saturated and one bin of view 5's over the counter, at 20 cm (in
    the air, 10 cm in front of the sphere)."""
    bad = hists.copy()
    bad[3, 4, :] = COUNTER
    bad[5, 4, 27] = COUNTER + 6
    return bad


def _ranges(points, view, poses):
    return np.linalg.norm(points - poses[view, :3, 3], axis=1)


def test_reprojection_on_the_tmf8820_puts_no_point_in_front_of_the_surface(tmf_sphere):
    """Under the whole pulse as a filter, bins of background alone cleared the threshold up to 35 cm in front of a
    strong return: 10 of 167 points lay behind the sensor, 28 over 5 cm off the sphere (Chamfer 38 mm)."""
    hists, poses, sensor = _load(tmf_sphere)
    pts, view, _, _ = reproject_points(hists, poses, sensor)
    assert len(pts) > 150
    assert _ranges(pts, view, poses).min() > 0.25, "the sphere's nearest point is 0.3 m from every view"
    _, dist, _ = trimesh.proximity.closest_point(builtin_scene("sphere"), pts)
    # The nearest surface in a zone's cone, placed on its axis: near the sphere, up to 10 cm off where the axis
    # passes the sphere's rim (9 such points, where the whole pulse as a filter gave 19 and points 35 cm off).
    assert np.median(dist) < 0.015 and (dist > 0.05).sum() <= 12 and dist.max() < 0.15


def test_a_return_at_zero_or_negative_range_gives_no_point(tmf_sphere, monkeypatch):
    hists, poses, sensor = _load(tmf_sphere)
    n, zones = hists.shape[:2]
    arrival = np.full((n, zones), sensor.zero_bin + 10.0)
    arrival[0, 0] = sensor.zero_bin - 2.0  # behind the sensor
    arrival[1, 1] = sensor.zero_bin  # at the sensor
    detected = np.ones((n, zones), bool)

    def found(*args, **kwargs):
        return FirstReturns(detected, arrival - 1, arrival, np.full((n, zones), 9.0), 5.0)

    monkeypatch.setattr(reproj, "first_returns", found)
    pts, view, zone, below = reproject_points(hists, poses, sensor)
    kept = set(zip(view.tolist(), zone.tolist()))
    assert (0, 0) not in kept and (1, 1) not in kept
    assert len(pts) == n * zones - 2 and below == 0
    assert np.all(_ranges(pts, view, poses) > 0)
    rep = reprojection(hists, poses, sensor)
    assert rep.behind_sensor == 2


def test_histograms_no_sensor_could_produce_are_found_in_summed_views_too(tmf_sphere):
    hists, _, sensor = _load(tmf_sphere)
    bad = _corrupt(hists).astype(np.float64)
    found = returns.impossible_counts(bad, sensor)
    assert set(zip(*np.nonzero(found))) == set(CORRUPT)
    assert not returns.impossible_counts(hists.astype(np.float64), sensor).any()
    # A first-photon sensor counts at most one photon a cycle: a histogram at its cycles exactly is possible.
    full = np.zeros((1, sensor.n_zones, sensor.n_bins))
    full[..., 5] = sensor.cycles
    assert not returns.impossible_counts(full, sensor).any()
    full[0, 2, 6] = 1
    assert returns.impossible_counts(full, sensor)[0].tolist() == [z == 2 for z in range(sensor.n_zones)]


def test_a_capture_without_impossible_counts_unmixes_as_before(tmf_sphere):
    """What carving and `fast` read stays the same where no histogram is impossible: every zone in the sum."""
    hists, _, sensor = _load(tmf_sphere)
    h = hists.astype(np.float64)
    signal, variance = photon_signal(h, sensor)
    marked, _ = photon_signal(h, sensor, np.ones(h.shape[:2], bool))
    np.testing.assert_array_equal(signal, marked)
    # The plain Sherman-Morrison unmixing over all nine zones, by hand.
    no_xt, _ = photon_signal(h, dataclasses.replace(sensor, crosstalk=0.0))
    c = sensor.crosstalk
    np.testing.assert_array_equal(signal, no_xt - c / (1 + c * 9) * no_xt.sum(axis=-2, keepdims=True))


def test_corrupt_zones_give_no_point_and_leave_the_other_zones_of_their_view_alone(tmf_sphere):
    """One saturated zone moved the eight other zones of its view to 4-9 cm from the sensor (12 bogus points from
    two corrupt histograms), and the zone over the counter gave a point where its bad bin lies."""
    hists, poses, sensor = _load(tmf_sphere)
    bad = _corrupt(hists)
    usable = ~implausible(bad, sensor.max_count, sensor.ignore_bins)
    assert set(zip(*np.nonzero(~usable))) == set(CORRUPT)
    clean = reprojection(hists, poses, sensor)
    rep = reprojection(bad, poses, sensor, usable=usable)
    kept = set(zip(rep.view.tolist(), rep.zone.tolist()))
    assert not kept & set(CORRUPT), "a histogram marked unusable gives no point"
    for v, _ in CORRUPT:
        others = rep.view == v
        assert others.sum() >= 7, "the other zones of the view keep their returns"
        assert _ranges(rep.points[others], rep.view[others], poses).min() > 0.25
    # Views without a corrupt zone reproject as before.
    same = ~np.isin(clean.view, [v for v, _ in CORRUPT])
    again = ~np.isin(rep.view, [v for v, _ in CORRUPT])
    np.testing.assert_array_equal(clean.points[same], rep.points[again])


def test_a_corrupt_zone_does_not_spoil_the_carving_limits_of_its_view(tmf_sphere):
    """Through the crosstalk unmixing, the saturated zone gave the eight other zones of its view a limit of
    -0.171 m: a whole good view carved nothing."""
    hists, _, sensor = _load(tmf_sphere)
    clean = carve_limits(hists, sensor, 5.0, 0.002)
    limits = carve_limits(_corrupt(hists), sensor, 5.0, 0.002)
    for v, zone in CORRUPT:
        others = np.arange(sensor.n_zones) != zone
        assert np.all(limits[v, others] > 0.2), limits[v]
        # Conservative: no zone carves deeper than it did with every zone's own counts.
        assert np.all(limits[v, others] <= clean[v, others] + 1e-9)
    rest = np.setdiff1d(np.arange(len(hists)), [v for v, _ in CORRUPT])
    np.testing.assert_array_equal(limits[rest], clean[rest])
    fr = first_returns(_corrupt(hists), sensor, 5.0, "leading")
    assert np.all(fr.onset_range_m(sensor)[3, np.arange(sensor.n_zones) != 4] > 0.2)


def test_the_baseline_leaves_out_what_its_warning_says_it_leaves_out(tmf_sphere, tmp_path, capsys):
    cap = tmp_path / "corrupt"
    assert cli_main(["simulate", "builtin:sphere", "--out", str(cap), "--sensor", "tmf8820", "--views", "24",
                     "--min-elevation", "20", "--seed", "0", "--no-progress"]) == 0
    chunk = cap / "chunk-000000" / "hists.npy"
    np.save(chunk, _corrupt(np.load(chunk)))
    out = tmp_path / "b"
    assert cli_main(["baseline", "reprojection", str(cap), "--out", str(out), "--no-gt"]) == 0
    assert "2 of 216 histograms no sensor could have produced" in capsys.readouterr().err
    points = np.asarray(trimesh.load(out / "points.ply").vertices)
    hists, poses, sensor = _load(cap)
    nearest = np.linalg.norm(points[:, None] - poses[None, :, :3, 3], axis=2).min(axis=1)
    assert nearest.min() > 0.25, "no point near a sensor"
    # The points of the usable histograms alone (the floor: z = 0, a simulated scene's): none from the zone over
    # the counter, which gave one in the air in front of the sphere.
    usable = ~implausible(hists, sensor.max_count, sensor.ignore_bins)
    expected = reprojection(hists, poses, sensor, usable=usable, floor_z=0.0).points
    np.testing.assert_allclose(np.sort(points, axis=0), np.sort(expected, axis=0), atol=1e-6)
    report = json.loads((out / "report.json").read_text())
    assert len(points) == report["reprojected_points"] and report["returns_behind_sensor"] == 0
