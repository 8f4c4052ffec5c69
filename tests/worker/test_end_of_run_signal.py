"""The end-of-run checks on the capture's signal, on the mesh's specks, and on pieces against a ground truth of
several: a dim capture that carving cut down to a lump says so; a spiky fit whose specks hold a share of the surface
no good fit leaves says so; two objects fitted as two pieces say nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from spadscan.worker.end_of_run import RunFacts, pieces_warning, specks_warning, warnings
from spadscan.worker.pieces import SPECKS_LIMIT, Pieces, mesh_pieces
from spadscan.worker.signal_check import NO_RETURN_LIMIT, Signal, capture_signal, signal_warning

pytestmark = pytest.mark.usefixtures("one_thread")


def facts(**extra) -> RunFacts:
    """A run that converged and has nothing else to say: only what `extra` adds can warn."""
    return RunFacts(stopped_by="converged", steps=100, model_converged=True, data_terms=[1.0] * 100, **extra)


def simulated_box(path, power: float):
    """16 simulated views of a 7 x 5 x 9 cm box at 0.3 m, the laser at `power` of the sensor model's."""
    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    mesh = trimesh.creation.box(extents=(0.07, 0.05, 0.09)).apply_translation([0.0, 0.0, 0.045])
    poses = fibonacci_hemisphere(16, 0.3, target=(0, 0, 0.05), min_elevation_deg=15)
    simulate_capture(mesh, sensor_preset("lcspc-sim"), poses, path,
                     settings=SimSettings(rays_per_zone=256, power=power), progress=False)
    capture = CaptureReader(path).load()
    return capture.by_pose().counts, capture.sensor


def test_signal_share_of_a_full_and_a_dim_capture(tmp_path):
    """At full power every histogram of the box holds a return at the carving threshold; at a 1/200 of it, most hold
    none, and the share passes the limit."""
    counts, sensor = simulated_box(tmp_path / "full", 1.0)
    full = capture_signal(counts, sensor, 5.0)
    counts, sensor = simulated_box(tmp_path / "dim", 0.005)
    dim = capture_signal(counts, sensor, 5.0)
    assert full.histograms == dim.histograms == 16
    assert full.share <= NO_RETURN_LIMIT < dim.share, (full, dim)
    usable = np.ones((16, 1), bool)
    usable[:4] = False  # histograms without data are not judged
    assert capture_signal(counts, sensor, 5.0, usable).histograms == 12


def test_a_dim_capture_warns_with_its_share_and_what_to_do():
    line = signal_warning(Signal(histograms=256, no_return=160, threshold=5.0))
    assert "too little signal: 62 % of the histograms (160 of 256)" in line
    assert "5 noise standard deviations" in line and "laser power" in line and "ambient" in line
    assert any(line == w for w in warnings(facts(signal=Signal(256, 160, 5.0))))
    assert warnings(facts(signal=Signal(256, 160, 5.0)))[0] == line  # first: it explains the doubts after it


def test_a_good_capture_stays_quiet():
    # The most no-return histograms a good fit's capture had: 3 of 540 (9 zones, a few at the object's edge).
    assert signal_warning(Signal(540, 3, 5.0)) is None
    assert warnings(facts(signal=Signal(540, 3, 5.0))) == []
    assert warnings(facts(signal=None)) == []


def box_with_specks(n: int, radius_m: float) -> trimesh.Trimesh:
    """A 3 cm cube (18 cm^2 of surface) and `n` droplets of `radius_m` floating around it."""
    parts = [trimesh.creation.box(extents=(0.03, 0.03, 0.03))]
    for i in range(n):
        a = 2 * math.pi * i / max(n, 1)
        parts.append(trimesh.creation.icosphere(1, radius_m).apply_translation([0.03 * math.cos(a),
                                                                                 0.03 * math.sin(a), 0.0]))
    return trimesh.util.concatenate(parts)


def test_specks_share_and_their_warning():
    """16 droplets of 1 mm radius round a 3 cm cube hold about 3 % of the surface, as the spiky cube's fit's did; 5 of
    0.5 mm about 0.3 %, as a good fit's do."""
    spiky = mesh_pieces(box_with_specks(16, 0.001))
    assert spiky.specks == 16 and spiky.specks_share > SPECKS_LIMIT
    assert spiky.count == 1 and pieces_warning(spiky) is None  # the pieces check passes it
    line = specks_warning(spiky)
    assert line.startswith(f"16 specks stand apart from the mesh, {100 * spiky.specks_share:.1f} % of its surface")
    assert line in warnings(facts(pieces=spiky))
    fine = mesh_pieces(box_with_specks(5, 0.0005))
    assert fine.specks == 5 and fine.specks_share < SPECKS_LIMIT
    assert specks_warning(fine) is None and warnings(facts(pieces=fine)) == []
    whole = mesh_pieces(trimesh.creation.box(extents=(0.03, 0.03, 0.03)))
    assert (whole.specks, whole.specks_share) == (0, 0.0)


def test_pieces_against_a_ground_truth_of_as_many():
    two = Pieces(count=2, share_apart=0.43, specks=0)
    assert pieces_warning(two, truth_pieces=2) is None
    assert warnings(facts(pieces=two, truth_pieces=2)) == []
    assert "the mesh is in 2 pieces" in pieces_warning(two, truth_pieces=1)
    assert "the mesh is in 2 pieces" in pieces_warning(two)  # no ground truth: the line stands
    assert "3 pieces" in pieces_warning(Pieces(count=3, share_apart=0.5, specks=0), truth_pieces=2)


def test_reconstruct_records_signal_specks_and_truth_pieces(tmp_path, monkeypatch):
    """The run's wiring: report.json holds the signal and the specks' share, and a two-piece ground truth silences the
    two-piece line (the two boxes' fit is in two pieces, as they are)."""
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture
    from spadscan.worker.reconstruct import reconstruct_capture

    pair = trimesh.util.concatenate([
        trimesh.creation.box(extents=(0.04, 0.04, 0.06)).apply_translation([-0.05, 0.0, 0.03]),
        trimesh.creation.box(extents=(0.04, 0.04, 0.06)).apply_translation([0.05, 0.0, 0.03])])
    pair.export(tmp_path / "pair.ply")
    poses = fibonacci_hemisphere(24, 0.4, target=(0, 0, 0.03), min_elevation_deg=15)
    simulate_capture(pair, sensor_preset("lcspc-sim"), poses, tmp_path / "cap",
                     settings=SimSettings(rays_per_zone=256), progress=False)
    report = reconstruct_capture(tmp_path / "cap", tmp_path / "out", steps=200, gt=tmp_path / "pair.ply",
                                 progress=False, device="cpu", threads=1,
                                 overrides={"mesh_resolution": 64, "early_stop": False})
    assert report["signal"]["histograms"] == 24 and report["signal"]["share"] <= NO_RETURN_LIMIT
    assert report["pieces"]["specks_share"] >= 0.0
    assert report["pieces"]["count"] == 2, report["pieces"]
    assert not any("pieces" in w for w in report["warnings"]), report["warnings"]
