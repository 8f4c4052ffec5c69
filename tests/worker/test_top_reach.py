"""Views aimed too low at a tall object never see its top, and the mesh is cut where they stopped: the run says so
when no view looked above the mesh's top; a top the views looked above, or a pointed one, says nothing."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker.top_reach import LIFT_M, MIN_TOP_WIDTH_M, UNSEEN_TOP_SHARE, TopReach, top_reach, top_warning

LCSPC = sensor_preset("lcspc-sim")


def block_vertices(height_m: float) -> np.ndarray:
    """The vertices of a 10 cm block `height_m` tall standing on z = 0, subdivided so that its top holds many."""
    block = trimesh.creation.box(extents=(0.1, 0.1, height_m)).apply_translation([0.0, 0.0, height_m / 2])
    return np.asarray(block.subdivide().subdivide().subdivide().vertices)


def test_a_top_the_views_looked_above_is_seen_and_one_at_their_reach_is_not():
    low = fibonacci_hemisphere(64, 0.5, max_elevation_deg=45)  # aimed at the floor, none from above
    full = fibonacci_hemisphere(64, 0.5)
    cut = top_reach(block_vertices(0.18), low, LCSPC)  # the views' fields end about there
    assert cut.share > UNSEEN_TOP_SHARE and cut.width_m >= MIN_TOP_WIDTH_M and cut.top_z == pytest.approx(0.18)
    line = top_warning(cut)
    assert line.startswith("no view looked above the mesh's top, at 0.18 m") and "aim the views higher" in line
    assert top_reach(block_vertices(0.18), full, LCSPC).share == 0.0  # the views from above looked there
    low_block = top_reach(block_vertices(0.05), low, LCSPC)
    assert low_block.share == 0.0 and top_warning(low_block) is None


def test_views_without_data_see_nothing():
    views = fibonacci_hemisphere(64, 0.5)
    usable = np.ones((64, 1), bool)
    assert top_reach(block_vertices(0.18), views, LCSPC, usable).share == 0.0
    assert top_reach(block_vertices(0.18), views, LCSPC, ~usable) is None
    high = fibonacci_hemisphere(64, 0.5)[:, :3, 3][:, 2] > 0.3
    usable[high] = False  # the views from above dropped their frames
    assert top_reach(block_vertices(0.18), views, LCSPC, usable).share > UNSEEN_TOP_SHARE


def test_a_pointed_top_or_a_seen_one_says_nothing():
    assert top_warning(TopReach(top_z=0.07, vertices=4, unseen=4, width_m=0.005)) is None  # an apex
    assert top_warning(TopReach(top_z=0.2, vertices=400, unseen=100, width_m=0.1)) is None
    assert top_warning(None) is None and top_reach(np.zeros((0, 3)), fibonacci_hemisphere(4, 0.5), LCSPC) is None
    assert top_warning(TopReach(top_z=0.2, vertices=400, unseen=390, width_m=0.1)).startswith("no view looked")
    assert f"{100 * LIFT_M:.0f} cm above it" in top_warning(TopReach(top_z=0.2, vertices=4, unseen=4, width_m=0.1))


@pytest.mark.usefixtures("one_thread")
def test_reconstruct_warns_of_a_tall_object_whose_top_no_view_saw(tmp_path):
    """A 30 cm block seen by views up to 40 degrees about its base: its hull ends where their fields do, and the run
    says so; the report keeps the figures."""
    from spadscan.worker.reconstruct import reconstruct_capture

    block = trimesh.creation.box(extents=(0.1, 0.1, 0.3)).apply_translation([0.0, 0.0, 0.15])
    poses = fibonacci_hemisphere(24, 0.5, min_elevation_deg=10, max_elevation_deg=40)
    simulate_capture(block, LCSPC, poses, tmp_path / "tall", settings=SimSettings(rays_per_zone=256), progress=False)
    report = reconstruct_capture(tmp_path / "tall", tmp_path / "out", steps=5, progress=False, device="cpu",
                                 threads=1, overrides={"mesh_resolution": 48, "early_stop": False})
    said = [w for w in report["warnings"] if w.startswith("no view looked above the mesh's top")]
    assert len(said) == 1, report["warnings"]
    assert report["top_reach"]["share"] > UNSEEN_TOP_SHARE and report["top_reach"]["top_z_m"] < 0.3
