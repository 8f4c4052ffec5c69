"""A capture's scene floor_z is checked where the capture is read: a value that is no height in metres (NaN, a bool,
a string, a huge number) is refused in one line naming scan.json, before anything is fitted."""

from __future__ import annotations

import json
import shutil

import pytest

from spadscan.protocol.errors import CaptureError
from spadscan.worker.recon.scene_data import load_scene


def with_floor(cylinder_capture, tmp_path, floor):
    path = tmp_path / "cap"
    shutil.copytree(cylinder_capture, path)
    manifest = json.loads((path / "scan.json").read_text())
    manifest.setdefault("scene", {})["floor_z"] = floor
    (path / "scan.json").write_text(json.dumps(manifest))
    return path


@pytest.mark.parametrize("floor", [float("nan"), float("inf"), True, "0.0", 1e300])
def test_a_floor_that_is_no_height_is_refused_in_one_line(cylinder_capture, tmp_path, floor):
    path = with_floor(cylinder_capture, tmp_path, floor)
    with pytest.raises(CaptureError, match=r"scan\.json: scene floor_z .* is not a height in metres") as err:
        load_scene(path)
    assert "\n" not in str(err.value)


def test_a_floor_in_metres_is_taken(cylinder_capture, tmp_path):
    assert load_scene(with_floor(cylinder_capture, tmp_path, -0.01)).scene["floor_z"] == -0.01
