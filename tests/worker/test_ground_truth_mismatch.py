"""A ground truth that plainly is not the scanned object in its frame and unit (moved by a metre, ten times its
size) is scored all the same, but `reconstruct` and `baseline` say so, in report.json's warnings and on the
terminal, as `eval` does: a Chamfer of hundreds of mm says that something is wrong, not what."""

from __future__ import annotations

import json

import pytest
import trimesh

from spadscan.cli import main
from spadscan.protocol.mesh_io import load_mesh_spec


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    """A capture of the built-in sphere (12 views), and its mesh moved by 1 m and scaled 10x, as OBJ files."""
    folder = tmp_path_factory.mktemp("mismatch")
    assert main(["simulate", "builtin:sphere", "--views", "12", "--rays-per-zone", "64", "--out",
                 str(folder / "cap"), "--no-progress"]) == 0
    mesh, _ = load_mesh_spec("builtin:sphere")
    mesh.copy().apply_translation([1.0, 0.0, 0.0]).export(folder / "moved.obj")
    mesh.copy().apply_scale(10.0).export(folder / "large.obj")
    trimesh.util.concatenate([mesh]).export(folder / "same.obj")
    return folder


def warnings_of(out) -> list[str]:
    return json.loads((out / "report.json").read_text())["warnings"]


@pytest.mark.parametrize("gt, said", [
    ("moved.obj", "the bounding boxes of the reconstruction and the ground truth do not overlap"),
    ("large.obj", "x the size of the reconstruction (bounding-box diagonals 3.46 and ")])
@pytest.mark.parametrize("command", ["reconstruct", "baseline"])
def test_a_ground_truth_unlike_the_reconstruction_is_said(sphere, tmp_path, capsys, gt, said, command):
    out = tmp_path / "out"
    argv = (["reconstruct", str(sphere / "cap"), "--steps", "5", "--threads", "1", "--no-progress"]
            if command == "reconstruct" else ["baseline", "reprojection", str(sphere / "cap"), "--points", "2000"])
    assert main(argv + ["--gt", str(sphere / gt), "--out", str(out)]) == 0
    (line,) = [w for w in warnings_of(out) if w.startswith("the ground truth ")]
    assert said in line and "check that it is the scanned object's, in metres, in the capture's frame" in line
    assert line in capsys.readouterr().err


def test_the_scanned_objects_own_ground_truth_says_nothing(sphere, tmp_path):
    out = tmp_path / "out"
    assert main(["baseline", "reprojection", str(sphere / "cap"), "--points", "2000", "--gt",
                 str(sphere / "same.obj"), "--out", str(out)]) == 0
    assert not [w for w in warnings_of(out) if w.startswith("the ground truth ")]
