"""Views from one elevation, or from above only, say so: every view of one ring reads nearly the same histogram, and a
fit of a bottle seen so came out 15-33 mm with no warning about its shape; views that all look down steeply flared a
block's sides (7-10 mm), every other check quiet."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from spadscan.protocol.schedules import elevation_rings, fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.protocol.scenes import builtin_scene
from spadscan.worker.view_spread import (ABOVE_ONLY_DEG, FAR_PATCH_M, LOW_ONLY_DEG, ONE_RING_DEG, SMALL_PATCH_RATIO,
                                         above_only_warning, far_views_warning, low_only_warning, one_ring_warning,
                                         small_object_warning, view_elevations_deg, zone_patch_m)


def test_one_ring_is_one_elevation_and_a_spiral_is_many():
    ring = elevation_rings(1, 16, 0.5, min_elevation_deg=20, max_elevation_deg=20)
    low, high, views = view_elevations_deg(ring, np.zeros(3))
    assert low == pytest.approx(20.0) and high - low == pytest.approx(0.0, abs=1e-6) and views == 16
    assert "16 views all stand 20 to 20 degrees up" in one_ring_warning(low, high, views)
    spiral = fibonacci_hemisphere(16, 0.5)
    low, high, views = view_elevations_deg(spiral, np.zeros(3))
    assert high - low > 45.0 and one_ring_warning(low, high, views) is None
    # Two rings 5 degrees apart or more are not one ring; two views are too few to judge.
    two = elevation_rings(2, 8, 0.5, min_elevation_deg=30, max_elevation_deg=30 + ONE_RING_DEG)
    assert one_ring_warning(*view_elevations_deg(two, np.zeros(3))) is None
    assert one_ring_warning(20.0, 20.0, 2) is None


def test_views_without_data_are_left_out():
    """A ring of views and one view high above it whose histograms hold no data: the capture is one ring."""
    poses = np.concatenate([elevation_rings(1, 8, 0.5, min_elevation_deg=20, max_elevation_deg=20),
                            fibonacci_hemisphere(1, 0.5, min_elevation_deg=80)])
    usable = np.ones((9, 1), bool)
    low, high, views = view_elevations_deg(poses, np.zeros(3))
    assert high - low > 50.0 and views == 9
    usable[8] = False
    low, high, views = view_elevations_deg(poses, np.zeros(3), usable)
    assert high - low == pytest.approx(0.0, abs=1e-6) and views == 8


@pytest.mark.usefixtures("one_thread")
def test_reconstruct_warns_of_a_capture_from_one_ring(tmp_path):
    from spadscan.worker.reconstruct import reconstruct_capture

    poses = elevation_rings(1, 12, 0.4, target=(0, 0, 0.05), min_elevation_deg=25, max_elevation_deg=25)
    simulate_capture(builtin_scene("sphere"), sensor_preset("lcspc-sim"), poses, tmp_path / "ring",
                     settings=SimSettings(rays_per_zone=256), progress=False)
    report = reconstruct_capture(tmp_path / "ring", tmp_path / "out", steps=5, progress=False, device="cpu",
                                 threads=1, overrides={"mesh_resolution": 48, "early_stop": False})
    assert any("12 views all stand" in w and "on one ring" in w for w in report["warnings"]), report["warnings"]


def test_views_from_above_only_are_said_and_a_band_reaching_lower_is_not():
    above = fibonacci_hemisphere(64, 0.5, min_elevation_deg=ABOVE_ONLY_DEG + 1)
    low, high, views = view_elevations_deg(above, np.zeros(3))
    assert low >= ABOVE_ONLY_DEG and views == 64
    said = above_only_warning(low, high, views)
    assert said.startswith(f"the 64 views all look down from {low:.0f} to {high:.0f} degrees up") and "\n" not in said
    lower = fibonacci_hemisphere(64, 0.5, min_elevation_deg=ABOVE_ONLY_DEG - 10)
    assert above_only_warning(*view_elevations_deg(lower, np.zeros(3))) is None
    assert above_only_warning(70.0, 80.0, 2) is None, "two views are too few to judge"
    assert above_only_warning(float("nan"), float("nan"), 0) is None


def test_views_from_low_down_only_are_said_and_a_band_reaching_higher_is_not():
    low_band = fibonacci_hemisphere(64, 0.5, min_elevation_deg=0, max_elevation_deg=LOW_ONLY_DEG)
    low, high, views = view_elevations_deg(low_band, np.zeros(3))
    assert high <= LOW_ONLY_DEG and views == 64
    said = low_only_warning(low, high, views)
    assert said.startswith(f"the 64 views all stand {low:.0f} to {high:.0f} degrees up from the scene's centre, none "
                           f"higher: the object's top is seen only at a grazing angle") and "\n" not in said
    higher = fibonacci_hemisphere(64, 0.5, min_elevation_deg=0, max_elevation_deg=LOW_ONLY_DEG + 10)
    assert low_only_warning(*view_elevations_deg(higher, np.zeros(3))) is None
    assert low_only_warning(*view_elevations_deg(fibonacci_hemisphere(256, 0.5), np.zeros(3))) is None
    assert low_only_warning(5.0, 10.0, 2) is None, "two views are too few to judge"
    assert low_only_warning(float("nan"), float("nan"), 0) is None


@pytest.mark.usefixtures("one_thread")
def test_reconstruct_warns_of_a_capture_from_low_down_only(tmp_path):
    from spadscan.worker.reconstruct import reconstruct_capture

    plate = trimesh.creation.cylinder(radius=0.1, height=0.01, sections=32).apply_translation([0.0, 0.0, 0.005])
    poses = fibonacci_hemisphere(24, 0.5, target=(0, 0, 0.005), min_elevation_deg=0, max_elevation_deg=20)
    simulate_capture(plate, sensor_preset("lcspc-sim"), poses, tmp_path / "low",
                     settings=SimSettings(rays_per_zone=256), progress=False)
    report = reconstruct_capture(tmp_path / "low", tmp_path / "out", steps=5, progress=False, device="cpu",
                                 threads=1, overrides={"mesh_resolution": 48, "early_stop": False})
    assert sum("24 views all stand" in w and "none higher" in w for w in report["warnings"]) == 1, report["warnings"]


@pytest.mark.usefixtures("one_thread")
def test_reconstruct_warns_of_a_capture_from_above_only(tmp_path):
    from spadscan.worker.reconstruct import reconstruct_capture

    poses = fibonacci_hemisphere(24, 0.4, target=(0, 0, 0.05), min_elevation_deg=65)
    simulate_capture(builtin_scene("sphere"), sensor_preset("lcspc-sim"), poses, tmp_path / "top",
                     settings=SimSettings(rays_per_zone=256), progress=False)
    report = reconstruct_capture(tmp_path / "top", tmp_path / "out", steps=5, progress=False, device="cpu",
                                 threads=1, overrides={"mesh_resolution": 48, "early_stop": False})
    assert any("24 views all look down from" in w for w in report["warnings"]), report["warnings"]


def test_a_zones_patch_grows_with_range_and_its_solid_angle():
    lcspc, tmf = sensor_preset("lcspc-sim"), sensor_preset("tmf8820")
    # lcspc-sim's one zone of 0.21 sr is a cone of about 15 degrees half-angle: 0.53 x the range across
    assert zone_patch_m(lcspc, 1.0) == pytest.approx(0.53, abs=0.01)
    assert zone_patch_m(lcspc, 0.5) == pytest.approx(0.5 * zone_patch_m(lcspc, 1.0))
    assert zone_patch_m(tmf, 1.0) < 0.5 * zone_patch_m(lcspc, 1.0)  # nine zones share a field of view like it


def test_views_from_far_away_are_said_and_the_benchmarks_ranges_are_not():
    lcspc, tmf = sensor_preset("lcspc-sim"), sensor_preset("tmf8820")
    near = FAR_PATCH_M / zone_patch_m(lcspc, 1.0)  # the range where a zone's patch is FAR_PATCH_M
    assert far_views_warning(lcspc, np.full(64, 0.47)) is None  # the benchmark's farthest lcspc-sim returns
    assert far_views_warning(tmf, np.full(64, 0.6)) is None  # the TMF8820's nine narrow zones
    said = far_views_warning(lcspc, np.r_[np.full(40, 0.74), np.full(20, 0.3)])
    assert said.startswith("the views' returns lie 0.74 m away (median), where each zone of the lcspc-sim sees a "
                           "patch 40 cm across:"), said
    assert said.endswith(f"scan closer (within {near:.2f} m, where a zone's patch is 27 cm or less)"), said
    assert far_views_warning(lcspc, np.full(2, 0.9)) is None  # two returns are too few to judge


@pytest.mark.usefixtures("one_thread")
def test_reconstruct_warns_of_a_capture_from_far_away(tmp_path):
    from spadscan.worker.reconstruct import reconstruct_capture

    poses = fibonacci_hemisphere(24, 0.85, target=(0, 0, 0.05))
    simulate_capture(builtin_scene("sphere"), sensor_preset("lcspc-sim"), poses, tmp_path / "far",
                     settings=SimSettings(rays_per_zone=256), progress=False)
    report = reconstruct_capture(tmp_path / "far", tmp_path / "out", steps=5, progress=False, device="cpu",
                                 threads=1, overrides={"mesh_resolution": 48, "early_stop": False})
    assert any(w.startswith("the views' returns lie 0.7") and "scan closer" in w for w in report["warnings"]), \
        report["warnings"]


def test_a_small_object_is_said_and_the_benchmarks_objects_are_not():
    """A zone that sees over SMALL_PATCH_RATIO times the object says so, with how near to come; the benchmark's
    objects (15-35 cm) are seen by patches up to 1.6 times their size, the TMF8820's nine zones far less."""
    lcspc, tmf = sensor_preset("lcspc-sim"), sensor_preset("tmf8820")
    returns = np.full(64, 0.45)
    patch = zone_patch_m(lcspc, 0.45)
    assert small_object_warning(lcspc, returns, 0.15) is None  # the pyramid, 15 cm, from 0.5 m
    assert small_object_warning(tmf, np.full(64, 0.3), 0.05) is None  # 5 cm seen by one of nine zones at 0.3 m
    assert small_object_warning(lcspc, returns, patch / SMALL_PATCH_RATIO * 1.01) is None
    said = small_object_warning(lcspc, returns, patch / SMALL_PATCH_RATIO * 0.99)
    assert said is not None and said.startswith("the object is small against the sensor's view")
    said = small_object_warning(lcspc, np.r_[np.full(40, 0.45), np.full(20, 0.2)], 0.03)
    near = SMALL_PATCH_RATIO * 0.03 / zone_patch_m(lcspc, 1.0)
    assert f"the mesh is 3.0 cm across, where each zone of the lcspc-sim sees a patch {100 * patch:.0f} cm" in said
    assert said.endswith(f"scan closer (within {near:.2f} m, where a zone's patch is {SMALL_PATCH_RATIO:g} times its "
                         f"size)"), said
    assert small_object_warning(lcspc, np.full(2, 0.45), 0.03) is None  # two returns are too few to judge
    assert small_object_warning(lcspc, returns, 0.0) is None  # a mesh of no extent says nothing of its size


@pytest.mark.usefixtures("one_thread")
def test_reconstruct_warns_of_a_small_object_and_not_of_far_views(tmp_path):
    """A 5 cm ball seen from 0.6 m: the small-object line says why the views were too far, and how near to come,
    in place of the far-views line."""
    from spadscan.worker.reconstruct import reconstruct_capture

    ball = trimesh.creation.icosphere(3, 0.025).apply_translation([0.0, 0.0, 0.025])
    poses = fibonacci_hemisphere(24, 0.6, target=(0, 0, 0.025))
    simulate_capture(ball, sensor_preset("lcspc-sim"), poses, tmp_path / "ball",
                     settings=SimSettings(rays_per_zone=4096), progress=False)
    report = reconstruct_capture(tmp_path / "ball", tmp_path / "out", steps=5, progress=False, device="cpu",
                                 threads=1, overrides={"mesh_resolution": 48, "early_stop": False})
    assert sum(w.startswith("the object is small against the sensor's view") for w in report["warnings"]) == 1, \
        report["warnings"]
    assert not any(w.startswith("the views' returns lie") for w in report["warnings"]), report["warnings"]


@pytest.mark.usefixtures("one_thread")
def test_a_fit_left_without_surface_names_the_views_from_low_down_in_its_error(tmp_path, monkeypatch):
    """A flat plate seen from 25 degrees up at most left the fit no surface at all: the error carries the line on the
    views, which needs only the capture."""
    from spadscan.worker.recon.errors import ReconstructionError
    from spadscan.worker.recon.fast.model import FastModel
    from spadscan.worker.reconstruct import reconstruct_capture

    def no_surface(self, resolution=None, averaged=True):
        raise ReconstructionError("no surface: the SDF is outside everywhere on the grid")

    monkeypatch.setattr(FastModel, "extract_mesh", no_surface)
    plate = trimesh.creation.cylinder(radius=0.1, height=0.01, sections=32).apply_translation([0.0, 0.0, 0.005])
    poses = fibonacci_hemisphere(24, 0.5, target=(0, 0, 0.005), min_elevation_deg=0, max_elevation_deg=20)
    simulate_capture(plate, sensor_preset("lcspc-sim"), poses, tmp_path / "low",
                     settings=SimSettings(rays_per_zone=256), progress=False)
    with pytest.raises(ReconstructionError) as err:
        reconstruct_capture(tmp_path / "low", tmp_path / "out", steps=5, progress=False, device="cpu", threads=1,
                            overrides={"mesh_resolution": 48})
    assert str(err.value).startswith("no surface: the SDF is outside everywhere on the grid; the 24 views all stand ")
    assert "none higher" in str(err.value) and "\n" not in str(err.value)
