"""A mesh that stops well above the floor its object stands on has lost its foot (views aimed high on a tall object
never looked there), or its object does not stand there: the run says so; a mesh down to its floor, or one on a
table, says nothing."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker.floor_gap import GAP_LIMIT_M, FloorGap, floor_gap, gap_warning


def block_vertices(bottom_m: float) -> np.ndarray:
    """The vertices of a 10 cm cube whose bottom face stands at `bottom_m`."""
    return np.asarray(trimesh.creation.box(extents=(0.1, 0.1, 0.1)).apply_translation([0, 0, bottom_m + 0.05])
                      .vertices)


def test_a_mesh_over_the_limit_above_its_floor_says_so_and_one_on_it_does_not():
    gap = floor_gap(block_vertices(0.047), 0.0, "config")
    assert gap.gap_m == pytest.approx(0.047) and gap.bottom_z == pytest.approx(0.047)
    line = gap_warning(gap)
    assert line.startswith("the mesh stops 4.7 cm above the floor it stands on (z = 0.000 m, field.floor_z)")
    assert "aim the views lower" in line
    assert gap_warning(floor_gap(block_vertices(0.047), 0.02, "capture")) is None  # 2.7 cm: within the limit
    assert gap_warning(floor_gap(block_vertices(0.02 + GAP_LIMIT_M + 0.001), 0.02, "capture")).endswith(
        "set the floor's height")
    assert gap_warning(floor_gap(block_vertices(0.0), 0.0, "config")) is None
    assert gap_warning(floor_gap(block_vertices(-0.01), 0.0, "config")) is None  # below it: the floor cut's check


def test_no_floor_a_table_or_no_mesh_is_not_judged():
    assert floor_gap(block_vertices(0.1), None, "config") is None
    assert floor_gap(block_vertices(0.1), 0.0, "table") is None
    assert floor_gap(block_vertices(0.1), float("nan"), "config") is None
    assert floor_gap(np.zeros((0, 3)), 0.0, "config") is None
    assert gap_warning(None) is None
    assert FloorGap(0.0, 0.05, "config").to_dict()["gap_m"] == pytest.approx(0.05)


@pytest.mark.usefixtures("one_thread")
def test_reconstruct_warns_of_a_mesh_that_stops_above_its_floor(tmp_path):
    """A 10 cm cube held 10 cm over the floor of a simulated scene, seen by 64 views of the TMF8820 model, whose low
    zones look under it and carve that space: its mesh stops there, and the run says so; the report keeps the
    figures."""
    from spadscan.worker.reconstruct import reconstruct_capture

    cube = trimesh.creation.box(extents=(0.1, 0.1, 0.1)).apply_translation([0.0, 0.0, 0.15])
    poses = fibonacci_hemisphere(64, 0.4, target=(0.0, 0.0, 0.1), max_elevation_deg=60)
    simulate_capture(cube, sensor_preset("tmf8820"), poses, tmp_path / "held", settings=SimSettings(rays_per_zone=128),
                     progress=False)
    report = reconstruct_capture(tmp_path / "held", tmp_path / "out", steps=5, progress=False, device="cpu",
                                 threads=1, overrides={"mesh_resolution": 48, "early_stop": False})
    said = [w for w in report["warnings"] if w.startswith("the mesh stops ")]
    assert len(said) == 1, report["warnings"]
    assert report["floor_gap"]["gap_m"] > GAP_LIMIT_M and report["floor_gap"]["floor"] == "config"
