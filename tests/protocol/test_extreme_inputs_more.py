"""Absurd numbers in the files users name: one clear line each, no numpy warning before it, the right thing named."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh

from spadscan.protocol.errors import DatasetError, MeshError
from spadscan.protocol.lcspc import import_lcspc
from spadscan.protocol.mesh_io import load_mesh
from spadscan.protocol.schedules import look_at


def sphere(radius: float, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    mesh.apply_translation(centre)
    return mesh


def write_obj(path, mesh: trimesh.Trimesh, scale: float = 1.0):
    """`mesh` scaled by `scale` as OBJ text with every digit of float64 (an export would round or overflow absurd
    coordinates, and trimesh's own scaling warn of overflows)."""
    lines = ["v %r %r %r" % tuple(float(x) * scale for x in v) for v in mesh.vertices]
    lines += ["f %d %d %d" % tuple(f + 1) for f in mesh.faces]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.filterwarnings("error")  # one line: no numpy RuntimeWarning printed before it
def test_an_stl_with_an_infinite_vertex_is_one_error_and_no_warning(tmp_path):
    mesh = sphere(0.1)
    vertices = mesh.vertices.copy()
    vertices[0] = np.inf
    with np.errstate(all="ignore"):  # the export's own normals; the test is of reading the file
        trimesh.Trimesh(vertices, mesh.faces, process=False).export(tmp_path / "inf.stl")
    with pytest.raises(MeshError, match="non-finite vertex coordinates"):
        load_mesh(tmp_path / "inf.stl")


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("scale,across", [(1e200, "3.46e+199 m across"), (1e20, "3.46e+19 m across")])
def test_a_mesh_of_absurd_size_is_said_to_be_so_not_degenerate(tmp_path, scale, across):
    """A 1e200 m mesh's area overflows: it was called "all triangles are degenerate (zero area)"."""
    path = write_obj(tmp_path / "huge.obj", sphere(0.1), scale)
    with pytest.raises(MeshError) as info:
        load_mesh(path, units="m")
    msg = str(info.value)
    assert across in msg and "check its units" in msg and "degenerate" not in msg and "\n" not in msg, msg


def test_a_ground_truth_1e17_m_across_even_as_millimetres_is_refused_and_a_thousandfold_one_is_not(tmp_path):
    """Eval against the first ran for good; the second is a units mix-up that eval's mismatch note is for."""
    path = write_obj(tmp_path / "gt.obj", sphere(0.1), 1e20)  # 3.5e19 units: millimetres by size, still 3.5e16 m
    with pytest.raises(MeshError, match=r"3\.46e\+16 m across \(read as millimetres\)"):
        load_mesh(path)
    path = write_obj(tmp_path / "big.obj", sphere(0.1), 1000)
    assert load_mesh(path, units="m").extents.max() == pytest.approx(200.0, rel=1e-3)


def look_at_pose(k: int, n: int) -> list[list[float]]:
    """Pose k of n on a ring 0.5 m around the origin, looking at it."""
    az = 2 * math.pi * k / n
    return look_at(0.5 * np.array([math.cos(az), math.sin(az), 0.5]), (0.0, 0.0, 0.0)).tolist()


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("far", [1e300, 1.7e308])
def test_a_pose_absurdly_far_away_is_named_by_its_own_index(tmp_path, far):
    """Squared, every pose's distance from the mean overflowed alike and pose 0 was named for pose 5."""
    rng = np.random.default_rng(0)
    records = [{"hists": rng.integers(0, 400, 1024).tolist(), "pose": look_at_pose(k, 8)} for k in range(8)]
    records[5]["pose"][0][3] = far
    src = tmp_path / "far.json"
    src.write_text(json.dumps(records))
    with pytest.raises(DatasetError) as info:
        import_lcspc(src, tmp_path / "cap")
    assert "pose 5 lies" in str(info.value) and "inf m" not in str(info.value), str(info.value)
    assert not (tmp_path / "cap").exists()
