"""A wrong time axis in a capture's sensor record (its bin width, its zero_bin) puts the returns where no surface of
the scene can be. It is refused before the fit, in one line that names the time axis and the ranges seen against the
scene's sphere (`time_axis.check_time_axis`), where carving blamed the scene's bound ("space carving removed
everything ... check scene.radius"), the floor's warning blamed the floor, or a TMF8820 capture on a table was fitted
14 m off with exit status 0."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import torch

from spadscan.cli import main as cli_main
from spadscan.protocol.errors import CaptureError
from spadscan.worker.reconstruct import check_returns
from spadscan.worker.time_axis import IN_SCENE_SHARE, check_time_axis, return_places, scene_views
from spadscan.worker.recon.scene_data import load_scene

GOOD_SHARE = 0.95
"""The least share of strong returns where the scene can be that a good capture is held to here: every good capture
measured had all of them there (1.0), far above the check's IN_SCENE_SHARE."""


@pytest.fixture(scope="module")
def tmf_table_capture(tmp_path_factory):
    """16 views of a cylinder on a wide dark slab (the table, z = 0) by the TMF8820 model, from 0.35 m."""
    import trimesh

    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    from worker_helpers import cylinder_mesh

    slab = trimesh.creation.box([1.0, 1.0, 0.02]).apply_translation([0.0, 0.0, -0.01])
    poses = fibonacci_hemisphere(16, 0.35, target=(0, 0, 0.04), min_elevation_deg=35)
    path = tmp_path_factory.mktemp("tmf") / "table"
    simulate_capture(trimesh.util.concatenate([cylinder_mesh(), slab]), sensor_preset("tmf8820"), poses, path,
                     settings=SimSettings(rays_per_zone=256), seed=4, progress=False, scene={"table": True})
    return path


def with_sensor(capture, out, **changes):
    """A copy of `capture` at `out` whose scan.json's sensor record has `changes`."""
    shutil.copytree(capture, out)
    manifest = json.loads((out / "scan.json").read_text())
    manifest["sensor"].update(changes)
    (out / "scan.json").write_text(json.dumps(manifest))
    return out


def refused_run(capture, tmp_path, capsys) -> str:
    """The one line `spadscan reconstruct` refuses `capture` with (exit status 1, no traceback, no result)."""
    code = cli_main(["reconstruct", str(capture), "--out", str(tmp_path / "out"), "--steps", "2", "--device", "cpu",
                     "--no-gt", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 1, err
    assert "\n" not in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()
    return err


def test_a_bin_width_of_a_metre_is_refused_as_the_time_axis_not_the_scene_bound(cylinder_capture, tmp_path,
                                                                                  capsys):
    line = refused_run(with_sensor(cylinder_capture, tmp_path / "cap", bin_width_m=1.0), tmp_path, capsys)
    assert "strong returns lie" in line and "m from the sensor, but the scene's sphere is" in line, line
    assert "sensor.bin_width_m (1 m a bin)" in line and "sensor.zero_bin" in line, line
    assert "scene.radius" not in line and "space carving" not in line, line


def test_a_zero_bin_far_off_is_refused_as_the_time_axis_not_the_floor(cylinder_capture, tmp_path, capsys):
    line = refused_run(with_sensor(cylinder_capture, tmp_path / "cap", zero_bin=1000), tmp_path, capsys)
    assert "before the time axis's zero" in line and "sensor.zero_bin (1000)" in line, line
    assert "floor" not in line, line


def test_a_sensor_touching_the_surface_is_named_first_not_only_the_time_axis(tmp_path, capsys):
    """A TMF8820 a few millimetres from a ball: pile-up puts the photons' peak bins before the time axis's zero, as a
    zero_bin set too late would. The refusal names the likelier cause first (a surface touching the sensor), then
    the zero bin; not the bin width, which no return near zero says anything of."""
    cap = tmp_path / "near"
    assert cli_main(["simulate", "builtin:sphere", "--no-progress", "--sensor", "tmf8820", "--views", "16",
                     "--target", "0", "0", "0.1", "--radius", "0.105", "--out", str(cap)]) == 0
    capsys.readouterr()
    line = refused_run(cap, tmp_path, capsys)
    assert "at the start of its range" in line and "a surface touching the sensor" in line, line
    assert line.index("surface touching") < line.index("sensor.zero_bin") and "bin_width_m" not in line, line


def test_a_tmf8820_capture_on_a_table_with_a_bin_width_of_a_metre_is_refused(tmf_table_capture, tmp_path, capsys):
    line = refused_run(with_sensor(tmf_table_capture, tmp_path / "cap", bin_width_m=1.0), tmp_path, capsys)
    assert "sensor.bin_width_m (1 m a bin)" in line, line


def test_the_baselines_refuse_it_as_the_time_axis_too(cylinder_capture, tmp_path, capsys):
    cap = with_sensor(cylinder_capture, tmp_path / "cap", bin_width_m=1.0)
    code = cli_main(["baseline", "space-carving", str(cap), "--out", str(tmp_path / "out"), "--no-gt"])
    err = capsys.readouterr().err.strip()
    assert code == 1 and "Traceback" not in err, err
    line = err.splitlines()[-1]  # after the floor's line
    assert line.startswith("spadscan: error: ") and "sensor.bin_width_m (1 m a bin)" in line, err
    assert "space carving" not in err and not (tmp_path / "out").exists(), err


def with_scene(capture, out, **changes):
    """A copy of `capture` at `out` whose scan.json's scene record has `changes`."""
    shutil.copytree(capture, out)
    manifest = json.loads((out / "scan.json").read_text())
    manifest.setdefault("scene", {}).update(changes)
    (out / "scan.json").write_text(json.dumps(manifest))
    return out


@pytest.mark.parametrize("command", ["reconstruct", "baseline"])
@pytest.mark.parametrize("changes, said", [({"center": [0, 0.1]}, "scene center [0, 0.1] is not a finite 3-vector"),
                                           ({"radius": "big"}, "scene radius big must be a positive number"),
                                           ({"radius": 1e300}, "scene radius 1e+300 must be a positive number of "
                                                               "metres, at most 10000"),
                                           ({"center": [0, 0, 1e300]},
                                            "scene center [0, 0, 1e+300] lies over 10000 m")])
def test_a_malformed_scene_sphere_is_one_line_in_both_commands(cylinder_capture, tmp_path, capsys, command, changes,
                                                               said):
    cap = with_scene(cylinder_capture, tmp_path / "cap", **changes)
    argv = ([command, str(cap)] if command == "reconstruct" else [command, "space-carving", str(cap)])
    code = cli_main([*argv, "--out", str(tmp_path / "out"), "--no-gt",
                     *(["--steps", "2", "--no-progress"] if command == "reconstruct" else [])])
    err = capsys.readouterr().err.strip()
    assert code == 1 and "Traceback" not in err and said in err.splitlines()[-1], err


def test_views_aimed_at_two_objects_are_not_refused(cylinder_capture):
    """Two rings of views half a metre and a metre apart, each aimed at its own object: the point nearest every
    boresight lies between the objects, nearer than either, and their returns were refused as beyond its sphere.
    Their boresights miss that point by more than MISS_RATIO: no point looked at is known, nothing is refused."""
    record, poses, counts, sensor, usable = scene_views(load_scene(cylinder_capture))
    for apart in (0.5, 1.0):
        moved = poses.copy()
        moved[:, 0, 3] += apart
        both = np.concatenate([poses, moved])
        assert return_places({}, both, np.concatenate([counts, counts]), sensor) is None
        check_time_axis(cylinder_capture, {}, both, np.concatenate([counts, counts]), sensor)


def test_the_live_fit_refuses_it_too(cylinder_capture, tmp_path):
    """A live fit tests the views so far with `check_returns`, as the final run does."""
    cap = with_sensor(cylinder_capture, tmp_path / "cap", bin_width_m=1.0)
    with pytest.raises(CaptureError, match=r"sensor\.bin_width_m"):
        check_returns(cap, load_scene(cap))


@pytest.mark.parametrize("fixture", ["cylinder_capture", "table_capture", "tmf_table_capture"])
def test_good_captures_have_their_returns_where_the_scene_can_be(request, fixture):
    cap = request.getfixturevalue(fixture)
    scene = load_scene(cap)
    places = return_places(*scene_views(scene))
    assert places is not None and places.inside.size > 0
    assert places.share >= GOOD_SHARE > IN_SCENE_SHARE
    check_time_axis(cap, *scene_views(scene))


def test_the_sphere_comes_from_the_scene_record_when_the_views_look_at_no_common_point(cylinder_capture, tmp_path):
    """Views that all look the same way meet at no point: without a scene record's sphere nothing bounds the
    returns and nothing is refused; with one, the wrong time axis is."""
    cap = with_sensor(cylinder_capture, tmp_path / "cap", bin_width_m=1.0)
    scene = load_scene(cap)
    poses = scene.poses.clone()
    poses[:, :3, :3] = poses[0, :3, :3]  # every boresight the first view's
    parallel = dataclasses.replace(scene, poses=poses, scene={})
    assert return_places(*scene_views(parallel)) is None
    check_time_axis(cap, *scene_views(parallel))
    with pytest.raises(CaptureError, match="the scene's sphere is"):
        check_time_axis(cap, *scene_views(dataclasses.replace(parallel, scene={"center": [0.0, 0.0, 0.04],
                                                                               "radius": 0.1})))


def test_two_neighbouring_views_turned_at_random_are_not_refused(cylinder_capture):
    """Two views 7 degrees apart around the object (3 cm at 0.3 m), each turned at random by 10 degrees (LCSPCData's
    `_random` captures: up to 13): their boresights cross wherever the turns put them, a few cm from the sensors
    even. No point they look at is known there (`BORESIGHT_SPREAD`), and their returns are not refused."""
    scene = load_scene(cylinder_capture)
    target = np.array([0.0, 0.0, 0.03])  # the fixture's
    rng = np.random.default_rng(0)
    first = scene.poses[0].double().numpy()
    around = np.eye(4)
    around[:3, :3] = _rotation(np.array([0.0, 0.0, 1.0]), np.radians(7))
    around[:3, 3] = target - around[:3, :3] @ target
    for _ in range(40):
        poses = np.stack([first, around @ first])
        for pose in poses:
            pose[:3, :3] = pose[:3, :3] @ _rotation(rng.normal(size=3), np.radians(10))
        two = dataclasses.replace(scene, counts=scene.counts[[0, 0]], cycles=scene.cycles[[0, 0]],
                                  valid=scene.valid[[0, 0]], usable=scene.usable[[0, 0]],
                                  poses=torch.as_tensor(poses, dtype=scene.poses.dtype))
        check_time_axis(cylinder_capture, *scene_views(two))


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """The rotation of `angle` radians about `axis` (Rodrigues)."""
    k = axis / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


@pytest.mark.dataset
@pytest.mark.parametrize("rel", ["real/pyramid/pyramid.json", "real/pyramid/pyramid_random.json",
                                 "simulated/bunny/bunny.json"])
def test_the_datasets_captures_have_their_returns_where_the_scene_can_be(lcspc_dataset, tmp_path, rel):
    """LCSPCData's real pyramid on its table (close views, 0.2-0.28 m from the point they look at, some turned at
    random) and its simulated bunny: all their strong returns where the scene can be (1.0)."""
    from spadscan.protocol.lcspc import import_lcspc

    import_lcspc(lcspc_dataset / rel, tmp_path / "cap")
    scene = load_scene(tmp_path / "cap")
    assert return_places(*scene_views(scene)).share >= GOOD_SHARE
    check_time_axis(tmp_path / "cap", *scene_views(scene))
