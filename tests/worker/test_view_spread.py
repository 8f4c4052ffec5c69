"""Views from one elevation, or from above only, say so: every view of one ring reads nearly the same histogram, and a
fit of a bottle seen so came out 15-33 mm with no warning about its shape; views that all look down steeply flared a
block's sides (7-10 mm), every other check quiet."""

from __future__ import annotations

import numpy as np
import pytest

from spadscan.protocol.schedules import elevation_rings, fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.protocol.scenes import builtin_scene
from spadscan.worker.view_spread import (ABOVE_ONLY_DEG, ONE_RING_DEG, above_only_warning, one_ring_warning,
                                         view_elevations_deg)


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


@pytest.mark.usefixtures("one_thread")
def test_reconstruct_warns_of_a_capture_from_above_only(tmp_path):
    from spadscan.worker.reconstruct import reconstruct_capture

    poses = fibonacci_hemisphere(24, 0.4, target=(0, 0, 0.05), min_elevation_deg=65)
    simulate_capture(builtin_scene("sphere"), sensor_preset("lcspc-sim"), poses, tmp_path / "top",
                     settings=SimSettings(rays_per_zone=256), progress=False)
    report = reconstruct_capture(tmp_path / "top", tmp_path / "out", steps=5, progress=False, device="cpu",
                                 threads=1, overrides={"mesh_resolution": 48, "early_stop": False})
    assert any("24 views all look down from" in w for w in report["warnings"]), report["warnings"]
