"""The end-of-run checks on the capture's signal, on the mesh's specks, on pieces against a ground truth of several and
on tunnels against the ground truth's: a dim capture that carving cut down to a lump says so; a spiky fit whose specks
hold a share of the surface no good fit leaves says so; two objects fitted as two pieces say nothing; holes that the
ground truth lacks say so."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from spadscan.worker.end_of_run import (EXTRA_TUNNELS, RunFacts, pieces_warning, specks_warning, tunnels_warning,
                                        warnings)
from spadscan.worker.pieces import SPECKS_LIMIT, Pieces, mesh_pieces
from spadscan.worker.carving.returns import first_returns, weak_level
from spadscan.worker.carving.space_carving import carve_limits
from spadscan.worker.signal_check import NO_RETURN_LIMIT, Signal, aimed_zones, capture_signal, signal_warning

pytestmark = pytest.mark.usefixtures("one_thread")


def facts(**extra) -> RunFacts:
    """A run that converged and has nothing else to say: only what `extra` adds can warn."""
    return RunFacts(stopped_by="converged", steps=100, model_converged=True, data_terms=[1.0] * 100, **extra)


def simulated(path, power: float, mesh=None, sensor: str = "lcspc-sim", target_z: float = 0.05):
    """(counts, sensor) of 16 simulated views at 0.3 m of `mesh` (a 7 x 5 x 9 cm box by default), without a table,
    the laser at `power` of the sensor model's."""
    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    if mesh is None:
        mesh = trimesh.creation.box(extents=(0.07, 0.05, 0.09)).apply_translation([0.0, 0.0, 0.045])
    poses = fibonacci_hemisphere(16, 0.3, target=(0, 0, target_z), min_elevation_deg=15)
    simulate_capture(mesh, sensor_preset(sensor), poses, path,
                     settings=SimSettings(rays_per_zone=256 if sensor == "lcspc-sim" else 64, power=power),
                     progress=False)
    capture = CaptureReader(path).load()
    return capture.by_pose().counts, capture.sensor


def small_ball(path, power: float):
    """A 6 cm ball seen by the 9-zone TMF8820 from 0.3 m, no table behind it: the outer zones look past it."""
    ball = trimesh.creation.icosphere(3, 0.03).apply_translation([0.0, 0.0, 0.03])
    return simulated(path, power, ball, "tmf8820", target_z=0.03)


def test_signal_share_of_a_full_and_a_dim_capture(tmp_path):
    """At full power every histogram of the box holds a return at carving's level; at a 1/200 of it, most hold
    none, and the share passes the limit."""
    counts, sensor = simulated(tmp_path / "full", 1.0)
    full = capture_signal(counts, sensor, 5.0, weak_threshold=4.0)
    counts, sensor = simulated(tmp_path / "dim", 0.005)
    dim = capture_signal(counts, sensor, 5.0, weak_threshold=4.0)
    assert full.histograms == dim.histograms == 16
    assert full.share <= NO_RETURN_LIMIT < dim.share, (full, dim)
    usable = np.ones((16, 1), bool)
    usable[:4] = False  # histograms without data are not judged
    assert capture_signal(counts, sensor, 5.0, usable).histograms == 12


def test_no_return_is_what_carving_empties_to_the_end_of_its_range(tmp_path):
    """Off a table carving stops at a run above its weak threshold (4): a histogram with one is not carved empty
    and is not counted, though nothing in it clears 5. At 0.01 of the power, 11 of the box's 16 histograms hold
    nothing above 5, and carving empties 5 of them."""
    counts, sensor = simulated(tmp_path / "faint", 0.01)
    for weak in (4.0, None):  # None: on a table, carving's default level
        signal = capture_signal(counts, sensor, 5.0, weak_threshold=weak)
        emptied = carve_limits(counts, sensor, 5.0, 0.0, "leading", weak)[:, 0] >= sensor.max_range_m
        assert signal.no_return == int(emptied.sum()), (weak, signal)
        assert signal.threshold == weak_level(5.0, weak)
    assert (capture_signal(counts, sensor, 5.0, weak_threshold=4.0).no_return
            < capture_signal(counts, sensor, 5.0).no_return)
    assert (weak_level(5.0, 4.0), weak_level(5.0, None), weak_level(3.0, 4.0)) == (4.0, 5.0, 3.0)


def test_the_zone_aimed_at_the_object_is_judged():
    from types import SimpleNamespace

    from spadscan.protocol.sensor_model import Zone
    from spadscan.protocol.sensor_presets import sensor_preset

    assert aimed_zones(sensor_preset("tmf8820")) == (4,)  # the centre of its 3 x 3
    assert aimed_zones(sensor_preset("lcspc-sim")) == (0,)
    quad = SimpleNamespace(zones=[Zone(kind="rect", tan_x=x, tan_y=y)
                                  for x in ((-0.2, 0.0), (0.0, 0.2)) for y in ((-0.2, 0.0), (0.0, 0.2))])
    assert aimed_zones(quad) == (0, 1, 2, 3)  # four meet on the boresight: all of them
    tilted = SimpleNamespace(zones=[Zone(kind="cone", half_angle_rad=0.1, axis=(math.sin(a), 0.0, math.cos(a)))
                                    for a in (0.5, 0.2, -0.3)])
    assert aimed_zones(tilted) == (1,)  # none holds it: the nearest


def test_a_9_zone_capture_without_a_table_stays_quiet_and_a_dim_one_warns(tmp_path):
    """A small ball seen by the nine zones with nothing behind it: at full power the six outer zones of most views see
    past it into empty space (59 % of all histograms hold no return) but the centre zone sees the ball in every
    view, and the run has nothing to say; at 1/5000 of the power the centre zone misses it in 15 of the 16 views."""
    counts, sensor = small_ball(tmp_path / "bright", 1.0)
    bright = capture_signal(counts, sensor, 5.0, weak_threshold=4.0)
    everywhere = ~first_returns(counts, sensor, 4.0, "leading").detected
    assert everywhere.mean() > 0.5  # the outer zones: no return, however bright the capture
    assert (bright.histograms, bright.no_return, bright.zones) == (16, 0, (4,))
    assert signal_warning(bright) is None and warnings(facts(signal=bright)) == []
    counts, sensor = small_ball(tmp_path / "dim", 2e-4)
    dim = capture_signal(counts, sensor, 5.0, weak_threshold=4.0)
    assert dim.share > NO_RETURN_LIMIT, dim
    line = signal_warning(dim)
    assert line.startswith(f"too little signal: {100 * dim.share:.0f} % of the histograms ({dim.no_return} of 16) of "
                           f"zone 5 of 9, the one aimed at the object, hold no return"), line
    assert warnings(facts(signal=dim))[0] == line


def test_histograms_of_a_few_stray_photons_hold_no_return_even_without_background():
    """Without ambient light one photon clears any level: 16 views of one or two photons each are a capture too dim
    to say anything, and say so; three photons or more in a histogram are judged by carving's level alone."""
    from spadscan.protocol.sensor_presets import sensor_preset

    sensor = sensor_preset("lcspc-sim").with_(background=0.0)
    counts = np.zeros((16, 1, sensor.n_bins), np.uint32)
    counts[:, 0, 300] = 1
    counts[::2, 0, 301] = 1
    stray = capture_signal(counts, sensor, 5.0, weak_threshold=4.0)
    assert (stray.histograms, stray.no_return) == (16, 16), stray
    assert signal_warning(stray).startswith("too little signal: 100 % of the histograms (16 of 16)")
    assert "or hold fewer than 3 photons" in signal_warning(stray)
    counts[:, 0, 300:303] = 1  # three photons in three neighbouring bins: judged by the level, a return
    assert capture_signal(counts, sensor, 5.0, weak_threshold=4.0).no_return == 0


def test_a_dim_capture_warns_with_its_share_and_what_to_do():
    line = signal_warning(Signal(histograms=256, no_return=106, threshold=4.0))
    assert "too little signal: 41 % of the histograms (106 of 256)" in line
    assert "4 noise standard deviations" in line and "laser power" in line and "ambient" in line
    assert "says nothing of the object or carved its whole field of view empty" in line
    assert "field.carve_threshold and field.carve_weak_threshold set lower by --set" in line  # the first alone: refused
    assert any(line == w for w in warnings(facts(signal=Signal(256, 106, 4.0))))
    assert warnings(facts(signal=Signal(256, 106, 4.0)))[0] == line  # first: it explains the doubts after it


def test_a_good_capture_stays_quiet():
    # Every good fit's capture had none in its aimed zone; the torus at 0.3 of its power had 4 of 256 (a bad fit the
    # check lets pass: docs/end_of_run.md).
    assert signal_warning(Signal(256, 4, 4.0)) is None
    assert warnings(facts(signal=Signal(256, 4, 4.0))) == []
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


def test_pieces_on_a_table_name_the_thin_sheets_emptied_there():
    two = Pieces(count=2, share_apart=0.19, specks=0)
    line = pieces_warning(two, thin_sheets_emptied=1752)
    assert "on the table the thin-sheets part emptied 1752 nodes" in line
    assert "--set parts.thin_sheets.enabled=false" in line and line.endswith("; look at preview.png")
    assert "thin-sheets" not in pieces_warning(two, thin_sheets_emptied=0)
    assert "thin-sheets" not in pieces_warning(two)  # no table: the part did not run
    assert pieces_warning(Pieces(count=1, share_apart=0.0, specks=0), thin_sheets_emptied=1752) is None
    assert warnings(facts(pieces=two, thin_sheets_emptied=1752)) == [line]


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
    assert report["signal"]["threshold"] == 4.0 and report["signal"]["zones"] == [0]  # carving's level: no table
    assert report["pieces"]["specks_share"] >= 0.0
    assert report["pieces"]["count"] == 2, report["pieces"]
    assert not any("pieces" in w for w in report["warnings"]), report["warnings"]


def test_a_faint_capture_carved_at_lowered_thresholds_still_warns(tmp_path):
    """At 0.01 of the power carving at its default level (4 off a table) empties several of the box's views and the
    run says so; with the thresholds lowered to 3 and 2 (what the first warning offers) noise clears the level in
    every view, the first line falls silent, and the second says the capture is faint by the default level. A
    bright capture refitted at the same lowered level says nothing."""
    counts, sensor = simulated(tmp_path / "faint", 0.01)
    as_shipped = capture_signal(counts, sensor, 5.0, weak_threshold=4.0, defaults=(5.0, 4.0))
    assert as_shipped.default_share is None and as_shipped.share > NO_RETURN_LIMIT  # judged at the default already
    lowered = capture_signal(counts, sensor, 3.0, weak_threshold=2.0, defaults=(5.0, 4.0))
    assert lowered.share <= NO_RETURN_LIMIT < lowered.default_share, lowered
    assert lowered.default_no_return == as_shipped.no_return and lowered.default_threshold == 4.0
    line = signal_warning(lowered)
    assert line.startswith(f"faint returns: {100 * lowered.default_share:.0f} % of the histograms "
                           f"({lowered.default_no_return} of 16) hold no return above carving's default level "
                           f"(4 "), line
    assert "this run carved at 2, its thresholds set lower" in line and "laser power" in line
    assert "lower thresholds will not help" in line and "preview.png" in line
    assert warnings(facts(signal=lowered))[0] == line
    assert lowered.to_dict()["default_share"] == lowered.default_share
    counts, sensor = simulated(tmp_path / "full", 1.0)
    bright = capture_signal(counts, sensor, 3.0, weak_threshold=2.0, defaults=(5.0, 4.0))
    assert bright.default_no_return == 0 and signal_warning(bright) is None


def test_reconstruct_at_lowered_thresholds_judges_a_faint_capture_at_the_default_level(tmp_path):
    """The run's wiring: a faint box refitted with the thresholds lowered records the default level's share in
    report.json and warns; the same run at the shipped thresholds records none (it was judged at that level)."""
    from spadscan.worker.reconstruct import reconstruct_capture

    simulated(tmp_path / "faint", 0.01)
    small = {"mesh_resolution": 48, "early_stop": False}
    lowered = reconstruct_capture(tmp_path / "faint", tmp_path / "low", steps=20, progress=False, device="cpu",
                                  threads=1, overrides={**small, "field.carve_threshold": 3.0,
                                                        "field.carve_weak_threshold": 2.0})
    assert lowered["signal"]["threshold"] == 2.0 and lowered["signal"]["default_threshold"] == 4.0
    assert lowered["signal"]["default_share"] > NO_RETURN_LIMIT >= lowered["signal"]["share"], lowered["signal"]
    assert any(w.startswith("faint returns: ") for w in lowered["warnings"]), lowered["warnings"]
    shipped = reconstruct_capture(tmp_path / "faint", tmp_path / "shipped", steps=20, progress=False, device="cpu",
                                  threads=1, overrides=small)
    assert shipped["signal"]["default_threshold"] is None and shipped["signal"]["default_share"] is None
    assert not any(w.startswith("faint returns: ") for w in shipped["warnings"]), shipped["warnings"]


def test_a_lowered_run_that_still_misses_the_object_is_not_told_to_lower_again():
    """At thresholds already below their defaults, the too-little-signal line gives the default level's share
    instead of offering lower ones (there noise passes for returns)."""
    lowered = Signal(histograms=256, no_return=40, threshold=2.0, default_threshold=4.0, default_no_return=119)
    line = signal_warning(lowered)
    assert line.startswith("too little signal: 16 % of the histograms (40 of 256)"), line
    assert "set lower by --set" not in line and "below their defaults already" in line
    assert "at the default level (4) 46 % hold none" in line
    assert "set lower by --set" in signal_warning(Signal(histograms=256, no_return=40, threshold=4.0))


def test_a_capture_too_faint_to_leave_a_surface_names_its_signal_in_the_error(tmp_path, monkeypatch):
    """The dimmest captures leave the fit no surface at all ("no surface: the SDF is outside everywhere", a torus at
    four times the ambient light): the error then carries the signal check's line, which needs only the capture.
    A capture with signal keeps the error as it was."""
    from spadscan.worker.recon.errors import ReconstructionError
    from spadscan.worker.recon.fast.model import FastModel
    from spadscan.worker.reconstruct import reconstruct_capture

    def no_surface(self, resolution=None, averaged=True):
        raise ReconstructionError("no surface: the SDF is outside everywhere on the grid")

    monkeypatch.setattr(FastModel, "extract_mesh", no_surface)
    run = dict(steps=5, progress=False, device="cpu", threads=1, overrides={"mesh_resolution": 48})
    simulated(tmp_path / "dim", 0.01)  # 5 of its 16 views empty at carving's level
    with pytest.raises(ReconstructionError) as err:
        reconstruct_capture(tmp_path / "dim", tmp_path / "out-dim", **run)
    assert str(err.value).startswith("no surface: the SDF is outside everywhere on the grid; too little signal: ")
    simulated(tmp_path / "full", 1.0)
    with pytest.raises(ReconstructionError) as err:
        reconstruct_capture(tmp_path / "full", tmp_path / "out-full", **run)
    assert str(err.value) == "no surface: the SDF is outside everywhere on the grid"


def tori(n: int, spacing_m: float = 0.12) -> trimesh.Trimesh:
    """`n` tori side by side, flat on the floor (8 cm across, holes 5 cm across): n pieces with a tunnel each."""
    return trimesh.util.concatenate([
        trimesh.creation.torus(0.04, 0.015).apply_translation([spacing_m * (i - (n - 1) / 2), 0.0, 0.015])
        for i in range(n)])


def test_tunnels_counted_on_the_pieces_of_note():
    """A sphere has none, a torus one, three tori three; specks do not count, and an open surface has no genus."""
    assert mesh_pieces(trimesh.creation.icosphere()).tunnels == 0
    assert mesh_pieces(tori(1)).tunnels == 1 and mesh_pieces(tori(3)).tunnels == 3
    assert mesh_pieces(trimesh.util.concatenate([trimesh.creation.box(extents=(0.1, 0.1, 0.1)),
                                                 tori(1).apply_scale(0.05)])).tunnels == 0  # a speck's tunnel
    sphere = trimesh.creation.icosphere()
    assert mesh_pieces(trimesh.Trimesh(sphere.vertices, sphere.faces[1:])).tunnels is None  # one face cut out
    assert mesh_pieces(tori(2)).to_dict()["tunnels"] == 2


def test_tunnels_beyond_the_ground_truths_warn():
    """More than EXTRA_TUNNELS tunnels beyond the ground truth's warn; as many as it has, or a few more (the pinholes of
    a good fit), or no ground truth or no genus say nothing."""
    three = mesh_pieces(tori(3))
    line = tunnels_warning(three, truth_tunnels=0)
    assert line.startswith("the mesh has 3 tunnels through it where its ground truth has 0: thin walls")
    assert "preview.png" in line and line in warnings(facts(pieces=three, truth_pieces=3, truth_tunnels=0))
    assert tunnels_warning(three, truth_tunnels=3) is None  # three handles, as the object has
    assert tunnels_warning(three, truth_tunnels=3 - EXTRA_TUNNELS) is None
    assert tunnels_warning(three, truth_tunnels=None) is None  # a capture alone does not tell
    assert tunnels_warning(Pieces(count=1, share_apart=0.0, specks=0, tunnels=None), truth_tunnels=0) is None
    assert warnings(facts(pieces=three, truth_pieces=3)) == []


@pytest.mark.slow
def test_reconstruct_warns_of_tunnels_its_ground_truth_lacks(tmp_path):
    """The run's wiring: three tori fitted and scored against three spheres (as many pieces, no tunnels) keep their
    holes, report.json counts them and the truth's, and the run warns; scored against the tori themselves it does
    not."""
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture
    from spadscan.worker.reconstruct import reconstruct_capture

    rings = tori(3)
    rings.export(tmp_path / "tori.ply")
    trimesh.util.concatenate([trimesh.creation.icosphere(2, 0.04).apply_translation([0.12 * (i - 1), 0.0, 0.04])
                              for i in range(3)]).export(tmp_path / "balls.ply")
    poses = fibonacci_hemisphere(32, 0.4, target=(0, 0, 0.0), min_elevation_deg=20)
    simulate_capture(rings, sensor_preset("lcspc-sim"), poses, tmp_path / "cap",
                     settings=SimSettings(rays_per_zone=256), progress=False)
    run = {"steps": 300, "progress": False, "device": "cpu", "threads": 1,
           "overrides": {"mesh_resolution": 96, "early_stop": False}}
    wrong = reconstruct_capture(tmp_path / "cap", tmp_path / "balls", gt=tmp_path / "balls.ply", **run)
    assert wrong["pieces"]["tunnels"] == 3 and wrong["pieces"]["truth_tunnels"] == 0, wrong["pieces"]
    assert any(w.startswith("the mesh has 3 tunnels through it where its ground truth has 0")
               for w in wrong["warnings"]), wrong["warnings"]
    right = reconstruct_capture(tmp_path / "cap", tmp_path / "tori", gt=tmp_path / "tori.ply", **run)
    assert right["pieces"]["truth_tunnels"] == 3
    assert not any("tunnels" in w for w in right["warnings"]), right["warnings"]
