"""The paper's baselines on simulated captures: first returns, space carving (a hull safe for thin parts),
reprojection, and the `spadscan baseline` command."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from spadscan.cli import main as cli_main
from spadscan.protocol.errors import CaptureError, ConfigError
from spadscan.protocol.scenes import builtin_scene
from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, Simulator, simulate_capture
from spadscan.worker.baselines.common import calibrate
from spadscan.worker.baselines.reprojection import reproject_points
from spadscan.worker.carving import carve_hull, first_returns
from spadscan.worker.carving.bounds import cube_around
from spadscan.worker.carving.space_carving import carve_limits
from spadscan.worker.ground_truth import object_on_table
from spadscan.worker.metrics import mesh_metrics
from spadscan.worker.recon.fast.config import fast_config
from spadscan.worker.recon.fast.problem import carve_keep_returns_m, carve_weak_threshold


def _render(mesh, sensor, poses, seed=1, **settings):
    sim = Simulator(mesh, sensor, SimSettings(rays_per_zone=settings.pop("rays", 1024), **settings), seed=seed)
    return sim.frames(poses).hists, sim.sensor


@pytest.fixture(scope="module")
def lamp():
    """The built-in lamp (16 mm stem) seen from 128 views on a hemisphere of 0.5 m, as in LCSPCData."""
    mesh = builtin_scene("lamp")
    poses = fibonacci_hemisphere(128, 0.5, max_elevation_deg=90)
    hists, sensor = _render(mesh, sensor_preset("lcspc-sim"), poses)
    return mesh, hists, poses, sensor


def _plate_at(distance, half_width=0.01):
    """A small square plate facing a sensor at the origin that looks along +z."""
    plate = trimesh.creation.box([2 * half_width, 2 * half_width, 0.002])
    plate.apply_translation([0, 0, distance + 0.001])
    return plate


@pytest.mark.parametrize("preset, zone, tol_m", [("lcspc-sim", 0, 0.0008), ("tmf8820", 4, 0.003)])
@pytest.mark.parametrize("filter", ["matched", "leading"])
@pytest.mark.parametrize("photons", [0.2, 1.0, 2.5])
def test_first_return_arrival_is_the_surface_range(preset, zone, tol_m, filter, photons):
    """At 0.2 photons a cycle and at the 1-2.5 of an ordinary capture, where pile-up raises the noise behind a
    return (a peak of the z-scores would lie up to a bin towards the sensor)."""
    distances = np.array([0.15, 0.2437, 0.31, 0.4])
    hists = []
    base = sensor_preset(preset)
    for d in distances:
        # About `photons` per cycle at every distance (signal ~ plate area / d^4): pile-up that Coates undoes.
        power = photons * d ** 4 / (base.signal_scale * 4e-4)
        h, sensor = _render(_plate_at(d), base, np.eye(4)[None], power=power)
        hists.append(h[0])
    fr = first_returns(np.stack(hists), sensor, filter=filter)
    assert fr.detected[:, zone].all()
    np.testing.assert_allclose(fr.arrival_range_m(sensor)[:, zone], distances, atol=tol_m)
    assert np.all(fr.onset_range_m(sensor)[:, zone] <= distances), "the onset lies in front of the surface"


def test_background_alone_holds_no_return():
    sensor = sensor_preset("lcspc-sim")
    behind = _plate_at(-0.3)  # out of the field of view: pure background, with pile-up
    hists, sensor = _render(behind, sensor, np.repeat(np.eye(4)[None], 200, axis=0), ambient=2e-3)
    assert hists.sum(axis=-1).max() > 0.5 * sensor.cycles, "strong enough background for pile-up to matter"
    assert not first_returns(hists, sensor).detected.any()


def test_carved_hull_keeps_a_thin_stem(lamp):
    mesh, hists, poses, sensor = lamp
    lo, hi = cube_around(np.array([-0.15, -0.15, 0.0]), np.array([0.15, 0.15, 0.25]))
    res = carve_hull(hists, poses, sensor, bounds_min=lo, bounds_max=hi, resolution=64, floor_z=0.0)
    voxel = float(res.voxel_m.max())
    pts, _ = trimesh.sample.sample_surface(mesh, 20000, seed=0)
    stem = pts[(np.hypot(pts[:, 0], pts[:, 1]) < 0.012) & (pts[:, 2] > 0.03) & (pts[:, 2] < 0.15)]
    assert len(stem) > 500
    assert res.contains(pts, voxel).mean() > 0.99
    assert res.contains(stem, voxel).mean() > 0.99, "the thin stem survives carving"
    # ... and the hull is a hull, not the whole box: most of the space around the lamp is carved.
    assert res.occupancy.mean() < 0.15
    hull = res.mesh()
    assert hull.is_watertight
    assert mesh_metrics(hull, mesh, n_points=20_000).chamfer_mm < 25.0


def test_a_high_threshold_tightens_the_hull(lamp):
    mesh, hists, poses, sensor = lamp
    lo, hi = cube_around(np.array([-0.15, -0.15, 0.0]), np.array([0.15, 0.15, 0.25]))
    vol = [carve_hull(hists, poses, sensor, bounds_min=lo, bounds_max=hi, resolution=48, threshold=t,
                      floor_z=0.0).occupancy.sum() for t in (5.0, 15.0)]
    assert vol[1] < vol[0]


def test_a_weak_level_stops_carving_at_faint_returns_and_leaves_strong_leading_edges(lamp):
    _, hists, poses, sensor = lamp
    strict = carve_limits(hists, sensor, 5.0, 0.002)
    weak = carve_limits(hists, sensor, 5.0, 0.002, weak_threshold=4.0)
    lower = carve_limits(hists, sensor, 4.0, 0.002)
    assert np.all(weak <= strict), "a weak level never carves more"
    assert 0 < np.mean(weak < strict) < 0.1, "a few zones held a faint run of bins in front of their strong return"
    # The threshold itself lowered moves the onset of many strong returns up their leading edges (half the zones).
    assert np.mean(lower < strict) > 0.3


def test_hull_sdf_is_negative_inside_and_positive_outside(lamp):
    _, hists, poses, sensor = lamp
    res = carve_hull(hists, poses, sensor, bounds_min=[-0.15, -0.15, -0.05], bounds_max=[0.15, 0.15, 0.25],
                     resolution=32, floor_z=0.0)
    sdf = res.sdf()
    assert sdf.shape == (32, 32, 32) and np.all(np.isfinite(sdf))
    assert np.all(sdf[res.occupancy] < 0) and np.all(sdf[~res.occupancy] > 0)
    centres = res.origin + np.argwhere(res.occupancy) * res.voxel_m
    assert res.contains(centres).all()
    assert not res.contains(np.array([[0.14, 0.14, 0.24]])).any()


def test_rect_zone_sensor_carves_too():
    """The TMF8820's nine rectangular zones (pile-up, crosstalk, 13.6 mm bins)."""
    mesh = builtin_scene("sphere")
    poses = fibonacci_hemisphere(64, 0.35, target=(0, 0, 0.1), min_elevation_deg=10, max_elevation_deg=80)
    hists, sensor = _render(mesh, sensor_preset("tmf8820"), poses, rays=256)
    lo, hi = cube_around(np.array([-0.15, -0.15, 0.0]), np.array([0.15, 0.15, 0.25]))
    res = carve_hull(hists, poses, sensor, bounds_min=lo, bounds_max=hi, resolution=48, floor_z=0.0)
    pts, _ = trimesh.sample.sample_surface(mesh, 10000, seed=0)
    assert res.contains(pts, float(res.voxel_m.max())).mean() > 0.99
    # Very strong returns clear the threshold far down the pulse's leading edge, so the hull is loose in front of
    # the sphere; still, most space well away from it is carved.
    centres = res.origin + np.argwhere(np.ones_like(res.occupancy)) * res.voxel_m
    far = np.linalg.norm(centres - [0, 0, 0.1], axis=1) > 0.16
    assert res.occupancy.ravel()[far].mean() < 0.6


def test_carve_hull_refuses_bad_input(lamp):
    _, hists, poses, sensor = lamp
    ok = dict(bounds_min=[0, 0, 0], bounds_max=[1, 1, 1], resolution=16)
    with pytest.raises(CaptureError, match="must exceed bounds_min"):
        carve_hull(hists, poses, sensor, **{**ok, "bounds_max": [1, -1, 1]})
    with pytest.raises(CaptureError, match="resolution"):
        carve_hull(hists, poses, sensor, **{**ok, "resolution": 1})
    with pytest.raises(CaptureError, match="histograms have shape"):
        carve_hull(hists[:, :, :100], poses, sensor, **ok)
    with pytest.raises(CaptureError, match="threshold"):
        carve_hull(hists, poses, sensor, **ok, threshold=0.0)
    with pytest.raises(CaptureError, match="weak detection threshold"):
        carve_hull(hists, poses, sensor, **ok, weak_threshold=float("nan"))


def test_reprojected_points_lie_on_the_surface(lamp):
    mesh, hists, poses, sensor = lamp
    pts, view, zone, _ = reproject_points(hists, poses, sensor)
    assert len(pts) > 0.9 * len(poses) and np.all(zone == 0)
    _, dist, _ = trimesh.proximity.closest_point(mesh, pts)
    # Points come from the nearest surface in a 30-degree cone, placed on the axis: near, not on, the surface.
    assert np.median(dist) < 0.02


@pytest.fixture
def quick_metrics(monkeypatch):
    """The project's metrics on fewer samples: a KD-tree query of 300,000 points lying centimetres off the other
    surface takes minutes on a loaded 2-core machine, and these tests check the plumbing, not the figures."""
    import functools

    import spadscan.worker.metrics as metrics

    monkeypatch.setattr(metrics, "mesh_metrics", functools.partial(metrics.mesh_metrics, n_points=20_000))


@pytest.fixture(scope="module")
def sphere_capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("cap")
    mesh = builtin_scene("sphere")
    poses = fibonacci_hemisphere(96, 0.5, max_elevation_deg=90)
    cap = simulate_capture(mesh, sensor_preset("lcspc-sim"), poses, root / "sphere",
                           settings=SimSettings(rays_per_zone=512), progress=False)
    gt = root / "sphere.ply"
    mesh.export(gt)
    return cap, gt


def _two_frames_a_pose(cap, out):
    """The capture with each pose's measurement stored twice (frames 0 and 1), as a scan with frames_per_pose 2."""
    shutil.copytree(cap, out)
    for chunk in out.glob("chunk-*"):
        for name in ("hists.npy", "poses.npy"):
            np.save(chunk / name, np.repeat(np.load(chunk / name), 2, axis=0))
        meta = json.loads((chunk / "meta.json").read_text())
        meta["measurements"] = [dict(m, frame=f) for m in meta["measurements"] for f in (0, 1)]
        (chunk / "meta.json").write_text(json.dumps(meta))
    manifest = json.loads((out / "scan.json").read_text())
    (out / "scan.json").write_text(json.dumps({**manifest, "frames_per_pose": 2}))
    return out


def _one_frame_of_twice_the_cycles(cap, out):
    """The capture with each histogram doubled and the sensor's cycles doubled: two identical frames summed."""
    shutil.copytree(cap, out)
    for hists in out.glob("chunk-*/hists.npy"):
        np.save(hists, np.load(hists) * 2)
    manifest = json.loads((out / "scan.json").read_text())
    manifest["sensor"]["cycles"] *= 2
    (out / "scan.json").write_text(json.dumps(manifest))
    return out


@pytest.mark.parametrize("method", ["space-carving", "reprojection"])
def test_a_baseline_reads_the_frames_of_a_pose_as_one_view(sphere_capture, tmp_path, method):
    """Two frames a pose are one view of twice the cycles, as the reconstruction reads them: the same result as
    their sum stored as one frame (read frame by frame, a pose alone passed as seen by two views and reprojection
    stacked its points twice)."""
    from spadscan.worker.baselines.run import run_baseline

    cap, _ = sphere_capture
    framed = run_baseline(_two_frames_a_pose(cap, tmp_path / "framed"), tmp_path / "a", method, resolution=48,
                          floor_z=None)
    summed = run_baseline(_one_frame_of_twice_the_cycles(cap, tmp_path / "summed"), tmp_path / "b", method,
                          resolution=48, floor_z=None)
    assert framed["views"] == summed["views"] == 96
    key = "hull_fraction" if method == "space-carving" else "reprojected_points"
    assert framed[key] == summed[key]
    assert trimesh.load(tmp_path / "a" / "mesh.ply").vertices.shape == trimesh.load(tmp_path / "b" /
                                                                                    "mesh.ply").vertices.shape


@pytest.mark.usefixtures("draws_off_screen")  # the report's preview.png
def test_baseline_command_writes_a_mesh_and_a_report(sphere_capture, tmp_path, capsys, quick_metrics):
    cap, gt = sphere_capture
    out = tmp_path / "carve"
    assert cli_main(["baseline", "space-carving", str(cap), "--out", str(out), "--gt", str(gt),
                     "--resolution", "48"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["method"] == "space-carving" and report["threshold"] == 5.0 and report["calibrated"] is False
    assert report["ground_truth"] == report["gt"] == str(gt)  # the key reconstruct and eval use too
    assert "standard deviations" in report["threshold_units"]
    for key in ("chamfer_mm", "accuracy_mm", "completeness_mm", "fscore_5mm", "normal_error_deg", "seconds"):
        assert np.isfinite(report[key])
    assert report["chamfer_mm"] < 30
    assert trimesh.load(out / "mesh.ply").is_watertight
    said = capsys.readouterr()
    assert "Chamfer" in said.out
    # The method's time apart from the run's (metrics and pictures), and a line before each of those long stages.
    build, total = map(float, re.search(r", ([0-9.]+) s to build, ([0-9.]+) s in all", said.out).groups())
    assert build == round(report["seconds"], 1) and total >= build
    assert "scoring against the ground truth on" in said.err and "drawing the pictures" in said.err
    assert (out / "preview.png").read_bytes()[:4] == b"\x89PNG"
    page = (out / "report.html").read_text()
    assert "space-carving" in page and f"{report['chamfer_mm']:.4g} mm" in page and 'src="preview.png"' in page


def test_a_baseline_overwriting_another_leaves_none_of_its_files(sphere_capture, tmp_path, quick_metrics):
    """Reprojection writes points.ply; space carving over it with --overwrite does not, and must not list it."""
    import os
    import time

    cap, gt = sphere_capture
    out = tmp_path / "b"
    assert cli_main(["baseline", "reprojection", str(cap), "--out", str(out), "--gt", str(gt)]) == 0
    first = json.loads((out / "report.json").read_text())["files"]
    assert "points.ply" in first and (out / "points.ply").exists()
    an_hour_ago = time.time() - 3600  # the first run's time
    for path in out.iterdir():
        os.utime(path, (an_hour_ago, an_hour_ago))
    assert cli_main(["baseline", "space-carving", str(cap), "--out", str(out), "--gt", str(gt), "--overwrite",
                     "--resolution", "48"]) == 0
    files = json.loads((out / "report.json").read_text())["files"]
    assert "points.ply" not in files and not (out / "points.ply").exists()
    # Every file it lists is there (preview.png among them only where meshes can be drawn off screen).
    assert {"mesh.ply", "report.json", "report.html"} <= set(files) <= {p.name for p in out.iterdir()}
    assert "points.ply" not in (out / "report.html").read_text()


def test_a_baseline_overwrite_refuses_a_ground_truth_from_the_result_it_replaces(sphere_capture, tmp_path,
                                                                                 quick_metrics, capsys):
    """--overwrite sets the previous result aside before the ground truth is read: its mesh passed as --gt is
    refused in one line naming it, the folder left as it was."""
    cap, gt = sphere_capture
    out = tmp_path / "b"
    assert cli_main(["baseline", "space-carving", str(cap), "--out", str(out), "--gt", str(gt),
                     "--resolution", "48"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert cli_main(["baseline", "space-carving", str(cap), "--out", str(out), "--gt", str(out / "mesh.ply"),
                     "--overwrite", "--resolution", "48"]) == 1
    (line,) = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert f"--gt {out / 'mesh.ply'} is a file of the result in --out {out}" in line, line
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_a_baseline_overwrite_that_fails_at_its_metrics_leaves_the_previous_result_whole(sphere_capture, tmp_path,
                                                                                           quick_metrics, capsys):
    """The new mesh and points are written before the metrics; a ground truth whose table lies above the object
    fails them: the folder holds the previous run's files as they were, none of the new ones."""
    cap, gt = sphere_capture
    out = tmp_path / "b"
    assert cli_main(["baseline", "reprojection", str(cap), "--out", str(out), "--gt", str(gt)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    slab = trimesh.creation.box((2, 2, 0.02)).apply_translation((0, 0, 0.49))
    ball = trimesh.creation.icosphere(3, radius=0.05).apply_translation((0, 0, 0.55))
    high = tmp_path / "high_table.ply"
    trimesh.util.concatenate([slab, ball]).export(high)
    capsys.readouterr()
    assert cli_main(["baseline", "reprojection", str(cap), "--out", str(out), "--gt", str(high), "--threshold", "8",
                     "--overwrite"]) == 1
    assert "spadscan: error:" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_the_users_own_files_beside_a_result_are_never_part_of_it(sphere_capture, tmp_path, quick_metrics):
    """A file of the user's in --out is not the run's however new its time stamp (copied with -p from a machine whose
    clock runs ahead, edited meanwhile): it is not listed in report.json, and neither a finished nor a failed
    --overwrite removes it."""
    import os
    import time

    cap, gt = sphere_capture
    out = tmp_path / "b"
    out.mkdir()
    notes = out / "notes.txt"
    notes.write_text("threshold looks too low\n")
    ahead = time.time() + 3600
    os.utime(notes, (ahead, ahead))
    assert cli_main(["baseline", "reprojection", str(cap), "--out", str(out), "--gt", str(gt)]) == 0
    assert "notes.txt" not in json.loads((out / "report.json").read_text())["files"]
    with notes.open("a") as f:  # edited in place between the runs, a newer time stamp again
        f.write("v2\n")
    assert cli_main(["baseline", "space-carving", str(cap), "--out", str(out), "--gt", str(gt), "--overwrite",
                     "--resolution", "48"]) == 0
    assert "notes.txt" not in json.loads((out / "report.json").read_text())["files"]
    assert cli_main(["baseline", "space-carving", str(cap), "--out", str(out), "--overwrite",
                     "--threshold", "inf"]) != 0
    assert notes.read_text() == "threshold looks too low\nv2\n"


def calibrated(method: str, thresholds, sphere_capture, out, monkeypatch) -> dict:
    """`spadscan baseline METHOD --calibrate` over `thresholds` (20,000 points a mesh); its report.json."""
    import spadscan.worker.baselines.common as common

    monkeypatch.setattr(common, "CALIBRATION_THRESHOLDS", tuple(thresholds))
    monkeypatch.setattr(common, "CALIBRATION_POINTS", 20_000)
    cap, gt = sphere_capture
    assert cli_main(["baseline", method, str(cap), "--out", str(out), "--gt", str(gt), "--calibrate"]) == 0
    return json.loads((out / "report.json").read_text())


def test_calibration_picks_the_best_threshold(sphere_capture, tmp_path, monkeypatch, quick_metrics):
    out = tmp_path / "reproj"
    report = calibrated("reprojection", (4.0, 12.0), sphere_capture, out, monkeypatch)
    table = report["calibration"]["table"]
    assert report["calibrated"] is True and [row["threshold"] for row in table] == [4.0, 12.0]
    best = min(table, key=lambda row: row["chamfer_mm"])
    assert report["threshold"] == best["threshold"]
    assert (out / "points.ply").exists() and report["reprojected_points"] > 50


def test_a_threshold_that_finds_nothing_is_one_row_of_the_calibration_not_its_end(sphere_capture, tmp_path,
                                                                                   monkeypatch, quick_metrics):
    """At a threshold no histogram reaches, space carving has no return to bound the scene with: that threshold
    gives no surface, and the search goes on to the others (it used to end the whole baseline)."""
    report = calibrated("space-carving", (4.0, 1e9), sphere_capture, tmp_path / "carve", monkeypatch)
    first, second = report["calibration"]["table"]
    assert report["threshold"] == 4.0 and first["chamfer_mm"] is not None
    assert second["chamfer_mm"] is None and "no histogram holds a return" in second["note"]


def test_a_threshold_whose_mesh_lies_under_the_table_cut_is_one_row_not_the_end():
    """Only table-level returns at one threshold: its mesh has nothing above the cut the ground truth is scored
    above, which ended the whole search (MeshError) though the other thresholds gave surfaces."""
    slab = trimesh.creation.box([2.0, 2.0, 0.1]).apply_translation([0, 0, -0.05])
    truth = object_on_table(trimesh.util.concatenate([slab, builtin_scene("sphere")]))
    on_the_table = trimesh.creation.box([0.2, 0.2, 0.002]).apply_translation([0, 0, 0.001])
    meshes = {1.0: builtin_scene("sphere"), 2.0: on_the_table}
    result = calibrate(lambda t: meshes[t], truth, thresholds=(1.0, 2.0), n_points=5_000)
    assert result.threshold == 1.0
    below = result.table[1]
    assert below["chamfer_mm"] is None and "nothing above z = 0.0050 m" in below["note"]


def test_calibration_needs_ground_truth(sphere_capture, tmp_path, capsys):
    cap, _ = sphere_capture
    assert cli_main(["baseline", "reprojection", str(cap), "--out", str(tmp_path / "x"), "--calibrate"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("spadscan: error:") and "--gt" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("option", [["--floor-z", "nan"], ["--edge-deg", "inf"]])
def test_non_finite_options_are_one_line_errors(sphere_capture, tmp_path, capsys, option):
    cap, _ = sphere_capture
    assert cli_main(["baseline", "space-carving", str(cap), "--out", str(tmp_path / "x"), *option]) == 1
    err = capsys.readouterr().err
    assert err.startswith("spadscan: error:") and option[0] in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("method", ["reprojection", "space-carving"])
@pytest.mark.parametrize("floor, message", [
    ("-156", "--floor-z -156 m lies 156 m below the lowest sensor position"),  # -156 mm typed: the hull 4x larger
    ("20", "--floor-z 20 m lies above every sensor position"),  # 20 mm typed
])
def test_a_floor_no_view_could_see_is_refused_in_one_line(sphere_capture, tmp_path, capsys, method, floor, message):
    cap, _ = sphere_capture
    assert cli_main(["baseline", method, str(cap), "--out", str(tmp_path / "x"), "--no-gt", "--floor-z", floor]) == 1
    err = capsys.readouterr().err
    assert err.startswith("spadscan: error: ") and err.count("\n") == 1 and message in err, err
    assert "(metres, not millimetres?)" in err and "--threshold" not in err
    assert not (tmp_path / "x").exists()


def test_a_floor_that_removes_every_return_is_named_not_the_threshold(sphere_capture, tmp_path, capsys):
    """The sphere stands 0..0.2 m tall, the sensors up to 0.5 m high: a floor at 0.3 m leaves no return. The error
    said to try a lower --threshold, which brings none back."""
    cap, _ = sphere_capture
    assert cli_main(["baseline", "reprojection", str(cap), "--out", str(tmp_path / "x"), "--no-gt",
                     "--floor-z", "0.3"]) == 1
    err = capsys.readouterr().err.splitlines()[-1]
    assert err.startswith("spadscan: error: ") and "found no surface" in err, err
    assert "the floor at z = 0.3 m removed" in err and "--floor-z" in err and "lower --threshold" not in err, err
    assert not (tmp_path / "x").exists()


def test_baselines_do_not_import_torch():
    code = ("import sys, spadscan.worker.baselines.run, spadscan.worker.baselines.reprojection, "
            "spadscan.worker.baselines.floor, spadscan.worker.table_height, spadscan.worker.pulse, "
            "spadscan.worker.carving; "
            "sys.exit('torch' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


@pytest.fixture(scope="module")
def measured_on_table(tmp_path_factory):
    """24 views of the built-in pyramid on a wide slab whose top lies at z = -0.12 m, by the TMF8820 model, with the
    capture marked as measured (as an import of the dataset's real pyramid is): its table is not at z = 0."""
    slab = trimesh.creation.box([1.2, 1.2, 0.02]).apply_translation([0.0, 0.0, -0.13])
    scene = trimesh.util.concatenate([builtin_scene("pyramid").apply_translation([0, 0, -0.12]), slab])
    poses = fibonacci_hemisphere(24, 0.35, target=(0, 0, -0.08), min_elevation_deg=30)
    path = tmp_path_factory.mktemp("table") / "pyramid"
    simulate_capture(scene, sensor_preset("tmf8820"), poses, path, settings=SimSettings(rays_per_zone=256), seed=2,
                     progress=False, scene={"real": True})
    return path


def test_a_measured_scene_stands_on_its_table_found_in_the_histograms(measured_on_table, sphere_capture):
    import json

    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.worker.baselines.floor import SIMULATED_FLOOR_Z, scene_floor

    height, source = scene_floor(CaptureReader(measured_on_table).load())
    assert height == pytest.approx(-0.12, abs=0.01) and source == "the table, found in the histograms"
    assert scene_floor(CaptureReader(sphere_capture[0]).load()) == (SIMULATED_FLOOR_Z, "a scene without a table: z = 0")
    data = CaptureReader(measured_on_table).load()
    for table, expected in (({"z": -0.2}, -0.2), ({"normal": [0, 0, 2], "offset": -0.3}, -0.15)):
        data.manifest["scene"]["table"] = table
        assert scene_floor(data) == (pytest.approx(expected), "the table the capture names")
    # As the reconstruction reads the scene: a table to fit is found in the histograms; none means z = 0.
    data.manifest["scene"]["table"] = {"z": -0.2, "fit": True}
    assert scene_floor(data) == (pytest.approx(-0.12, abs=0.01), "the table, found in the histograms")
    for table in (False, None):
        data.manifest["scene"]["table"] = table
        assert scene_floor(data) == (SIMULATED_FLOOR_Z, "a scene without a table: z = 0")
    data.manifest["scene"]["table"] = {"normal": [0, 1, 1], "offset": 0.0}
    assert scene_floor(data) == (None, "a tilted table: no horizontal floor")
    data.manifest["scene"]["table"] = {"z": "low"}
    with pytest.raises(CaptureError, match="scene table needs a number 'z'"):
        scene_floor(data)
    manifest = json.loads((measured_on_table / "scan.json").read_text())
    assert "table" not in manifest["scene"]


def test_the_baseline_command_uses_the_table_unless_told(measured_on_table, tmp_path, capsys):
    out = tmp_path / "auto"
    assert cli_main(["baseline", "reprojection", str(measured_on_table), "--out", str(out), "--no-gt"]) == 0
    assert "floor at z = -0.1" in capsys.readouterr().err
    report = json.loads((out / "report.json").read_text())
    assert report["floor_z_m"] == pytest.approx(-0.12, abs=0.01)
    assert report["floor_source"] == "the table, found in the histograms"
    lowest = trimesh.load(out / "points.ply").vertices[:, 2].min()
    assert lowest < -0.05, "points of the object's lower part are kept"
    assert cli_main(["baseline", "reprojection", str(measured_on_table), "--out", str(tmp_path / "zero"),
                     "--no-gt", "--floor-z", "0"]) == 0
    assert trimesh.load(tmp_path / "zero" / "points.ply").vertices[:, 2].min() >= -0.005
    assert json.loads((tmp_path / "zero" / "report.json").read_text())["floor_source"] == "given"
    with pytest.raises(SystemExit):
        cli_main(["baseline", "reprojection", str(measured_on_table), "--out", str(tmp_path / "x"), "--floor-z",
                  "0", "--no-floor"])
    assert "not allowed with argument" in capsys.readouterr().err


@pytest.mark.parametrize("method, option, message", [
    ("space-carving", ["--surface", "convex-hull"], "--surface: only reprojection reads it, not space-carving"),
    ("reprojection", ["--resolution", "32"], "--resolution: only space-carving reads it, not reprojection"),
    ("reprojection", ["--edge-deg", "2", "--margin-mm", "3"],
     "--margin-mm, --edge-deg: only space-carving reads them, not reprojection"),
])
def test_an_option_the_method_does_not_read_is_refused(sphere_capture, tmp_path, capsys, method, option, message):
    cap, _ = sphere_capture
    assert cli_main(["baseline", method, str(cap), "--out", str(tmp_path / "x"), "--no-gt", *option]) == 1
    assert capsys.readouterr().err == f"spadscan: error: {message}\n"
    assert not (tmp_path / "x").exists()


def test_carving_keeps_the_top_of_a_tall_object_that_few_views_see():
    # Views aim at the origin from 0.5 m, so the top of a 34 cm column lies in only the few fields of view above
    # it: the rule that drops space fewer than 3 views see (unscanned corners of the box) cut it off, though those
    # views' first returns land on it. Space just beyond a first return stays.
    column = trimesh.creation.cylinder(radius=0.06, height=0.34, sections=48)
    column.apply_translation([0, 0, 0.17])
    poses = fibonacci_hemisphere(128, 0.5, max_elevation_deg=90)
    hists, sensor = _render(column, sensor_preset("lcspc-sim"), poses)
    lo, hi = cube_around(np.array([-0.12, -0.12, 0.0]), np.array([0.12, 0.12, 0.4]))
    pts, _ = trimesh.sample.sample_surface(column, 20000, seed=0)
    top = pts[pts[:, 2] > 0.3]
    kept = {}
    for keep_m in (0.0, fast_config().field.carve_keep_returns_m):
        res = carve_hull(hists, poses, sensor, bounds_min=lo, bounds_max=hi, resolution=64, floor_z=0.0,
                         keep_returns_m=keep_m)
        voxel = float(res.voxel_m.max())
        kept[keep_m] = res.contains(top, voxel).mean()
        if keep_m:
            assert res.contains(pts, voxel).mean() > 0.99
            # Still a hull, not the box: space well away from the column is carved.
            centres = res.origin + np.argwhere(np.ones_like(res.occupancy)) * res.voxel_m
            far = np.hypot(centres[:, 0], centres[:, 1]) > 0.1
            assert res.occupancy.reshape(-1)[far].mean() < 0.05
    assert kept[0.0] < 0.5 and kept[keep_m] > 0.95, kept
    with pytest.raises(CaptureError, match="keep_returns_m"):
        carve_hull(hists, poses, sensor, bounds_min=lo, bounds_max=hi, resolution=8, keep_returns_m=float("nan"))


def test_the_fast_hull_keeps_returns_beyond_few_views_on_simulated_captures_only():
    field = fast_config().field
    assert field.carve_keep_returns_m > 0
    assert carve_keep_returns_m(SimpleNamespace(real=False), field) == field.carve_keep_returns_m
    assert carve_keep_returns_m(SimpleNamespace(real=True), field) == 0.0
    for bad in (-0.01, float("nan"), 2.0, True):
        config = fast_config()
        config.field.carve_keep_returns_m = bad
        with pytest.raises(ConfigError, match="field.carve_keep_returns_m"):
            config.check()


def test_faint_runs_stop_carving_only_without_a_table():
    field = fast_config().field
    assert carve_weak_threshold(field, on_table=False) == field.carve_weak_threshold < field.carve_threshold
    assert carve_weak_threshold(field, on_table=True) is None


def test_the_fast_presets_hull_reads_the_frames_of_a_pose_as_one_view(sphere_capture, tmp_path):
    """The fit sums a pose's frames; its carved hull must read them as that one view too."""
    import torch

    from spadscan.worker.recon.fast.config import fast_config
    from spadscan.worker.recon.fast.problem import build_problem
    from spadscan.worker.recon.forward import choose_terms
    from spadscan.worker.recon.scene_data import load_scene

    cap, _ = sphere_capture
    hulls = []
    for path in (_two_frames_a_pose(cap, tmp_path / "framed"), _one_frame_of_twice_the_cycles(cap, tmp_path / "s")):
        scene = load_scene(path)
        hulls.append(build_problem(scene, fast_config(), "cpu", choose_terms(scene)).hull.sdf.detach())
    assert hulls[0].shape == hulls[1].shape and torch.equal(hulls[0], hulls[1])


def test_space_carving_on_fewer_views_than_it_needs_says_so(sphere_capture, tmp_path, capsys):
    """Two views: no space is seen by the three carving asks for, whatever the threshold (it said to lower it)."""
    cap, _ = sphere_capture
    two = tmp_path / "two"
    shutil.copytree(cap, two)
    for chunk in sorted(two.glob("chunk-*"))[1:]:
        shutil.rmtree(chunk)
    (chunk,) = two.glob("chunk-*")
    for name in ("hists.npy", "poses.npy"):
        np.save(chunk / name, np.load(chunk / name)[:2])
    meta = json.loads((chunk / "meta.json").read_text())
    (chunk / "meta.json").write_text(json.dumps({**meta, "measurements": meta["measurements"][:2]}))
    assert cli_main(["baseline", "space-carving", str(two), "--out", str(tmp_path / "out"), "--no-gt"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "at least 3 views" in err and "holds 2" in err and "--threshold" not in err
    assert not (tmp_path / "out").exists()


def test_a_baseline_that_cannot_draw_its_preview_says_why_in_its_report(sphere_capture, tmp_path, monkeypatch,
                                                                        quick_metrics):
    """As a reconstruction's report does (test_preview_warning.py): the dashboard, perhaps on another machine, reads
    the reason there. Before: said on stderr alone, the report silent."""
    from spadscan.dashboard.results import WORKER_CANNOT_DRAW, no_preview
    from test_preview_warning import cannot_draw_off_screen

    cap, gt = sphere_capture
    out = tmp_path / "carve"
    cannot_draw_off_screen(monkeypatch)
    assert cli_main(["baseline", "space-carving", str(cap), "--out", str(out), "--gt", str(gt),
                     "--resolution", "48"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert not (out / "preview.png").exists()
    (line,) = [w for w in report["warnings"] if w.startswith("no preview.png: ")]
    assert no_preview(report["warnings"]) == {"said": WORKER_CANNOT_DRAW, "why": line}
