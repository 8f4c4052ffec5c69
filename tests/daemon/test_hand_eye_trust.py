"""What `spadscan calibrate hand-eye` says about its own fit can be trusted: a start turned about the sensor's axis
comes back, a plane given at the wrong height is warned about by name, a zone whose predicted return misses the
observed one is counted as lost (not as a match) before and after the fit, and damaged tcp_pose metadata is one line."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spadscan.cli import main
from spadscan.daemon.arm.pose_convert import rotvec_to_matrix
from spadscan.daemon.hand_eye import (MIN_RANGE_M, WINDOW_BINS, Target, _Predictor, capture_tcp_poses, fit_hand_eye,
                                      peak_bins, peak_positions)
from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, Simulator
from test_hand_eye import X_TRUE, _BoxOnTable, errors, make_capture, sensor_poses, wrong_x

PLANE = Target("plane", (0, 0, 0))


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """The table seen from 24 views tilted every way, recorded with a bracket's drawing 6 mm and 2.3 deg off."""
    path = tmp_path_factory.mktemp("trust") / "table"
    make_capture(path, wrong_x())
    return path


def warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if "warning" in line]


def test_a_start_turned_180_degrees_about_the_boresight_comes_back(tmp_path, capsys):
    """A connector fitted the other way round from the drawing: the local fit settled 98 mm and 145 degrees off at
    8.6 mm RMS, with a warning that blamed the target first."""
    turned = X_TRUE.copy()
    turned[:3, :3] = X_TRUE[:3, :3] @ rotvec_to_matrix([0.0, 0.0, math.pi])
    make_capture(tmp_path / "turned", turned)
    fit = fit_hand_eye(tmp_path / "turned", PLANE)
    mm, deg = errors(fit.hand_eye)
    assert mm < 1.0 and deg < 0.3, (mm, deg)
    assert fit.turn_deg == 180 and fit.implausible() == [] and fit.rms_mm < 0.5
    assert main(["calibrate", "hand-eye", str(tmp_path / "turned"), "--plane", "0,0,0,0,0,1"]) == 0
    out, err = capsys.readouterr()
    assert warnings(err) == [], err
    assert "turned 180 deg about the sensor's axis" in out and "a connector turned from the drawing?" in out


@pytest.mark.parametrize("height_mm", [50, 80])
def test_a_plane_measured_with_the_wrong_tcp_is_warned_about_by_its_height(capture, capsys, height_mm):
    """The table measured with the bare flange's TCP active instead of a 50-80 mm pointer's: the fit took the height
    into X along the sensor's axis (52-84 mm off), left 1.4-2.2 mm RMS and a 0.3 mm uncertainty along z, and printed
    it without a word."""
    plane = f"0,0,{height_mm / 1000},0,0,1"
    assert main(["calibrate", "hand-eye", str(capture), "--plane", plane]) == 0
    out, err = capsys.readouterr()
    assert "hand_eye = [[" in out
    lines = warnings(err)
    assert len(lines) == 1 and "warning: implausible fit" in lines[0], err
    assert "mm along its axis" in lines[0]
    causes = lines[0][lines[0].index("likely"):]
    assert causes.startswith("likely the target's height") and "wrong TCP" in causes, causes


def test_a_right_plane_from_a_drawing_is_not_warned_about(capture):
    """The tighter limit along the axis for a start from a drawing leaves a right fit alone."""
    fit = fit_hand_eye(capture, PLANE)
    assert fit.implausible() == [] and fit.along_limit_mm == 20


def test_a_return_far_from_the_start_prediction_is_not_scored_as_a_match(capture, capsys):
    """The plane given 12 cm too high: every zone's predicted return lies about 9 bins (120 mm) from the observed
    one, outside its window, and the start's residual RMS read 8.8 mm (the centroid of the predicted background in
    the observed window) - less than when the plane was given 5 cm too high."""
    fit = fit_hand_eye(capture, Target("plane", (0, 0, 0.12)))
    assert math.isnan(fit.rms_start_mm) and fit.lost_start == fit.returns == 216
    assert main(["calibrate", "hand-eye", str(capture), "--plane", "0,0,0.12,0,0,1"]) == 0
    out = capsys.readouterr().out
    assert "it puts all 216 of these returns more than 2 bins = 27 mm off" in out, out


def _in_window(path, x: np.ndarray, target: Target) -> tuple[np.ndarray, np.ndarray]:
    """(zones that show a return, zones whose predicted return at X peaks within that return's window)."""
    reader = CaptureReader(path)
    data = reader.load()
    first_bin = int(math.ceil(data.sensor.bin_of_range(MIN_RANGE_M)))
    windows = peak_bins(data.hists, first_bin)
    shown = np.isfinite(peak_positions(data.hists, windows))
    counts, seen = _Predictor(data.sensor, target).counts(capture_tcp_poses(reader, data) @ x)
    return shown, shown & seen & (np.abs(peak_bins(counts, first_bin) - windows) <= WINDOW_BINS)


def test_returns_are_counted_only_where_the_prediction_lies_in_their_window(tmp_path, capsys):
    """A box on the table under the right X: every zone that sees the box was counted among the returns on the plane
    (216 of 216), and the start's RMS covered other zones than the fitted one."""
    make_capture(tmp_path / "box", X_TRUE, target=_BoxOnTable())
    fit = fit_hand_eye(tmp_path / "box", PLANE)
    shown, matched = _in_window(tmp_path / "box", fit.hand_eye, PLANE)
    assert fit.returns == matched.sum() and fit.returns + fit.lost == shown.sum()
    assert fit.lost > 0
    _, at_start = _in_window(tmp_path / "box", X_TRUE, PLANE)
    assert fit.returns - fit.lost_start == (matched & at_start).sum()
    assert main(["calibrate", "hand-eye", str(tmp_path / "box"), "--plane", "0,0,0,0,0,1"]) == 0
    out = capsys.readouterr().out
    assert f"{fit.returns} zone returns on the plane ({fit.lost} more off it at the fitted hand_eye" in out, out


def _damaged(tcp: np.ndarray) -> dict:
    """Ways a measurement's tcp_pose can be damaged, by name."""
    scaled = tcp.copy()
    scaled[:3, :3] *= 1.5
    return {"ragged": [[1, 0, 0], [0, 1, 0, 0]], "a string": "home", "3x3": np.eye(3).tolist(),
            "a dict": {"x": 1}, "not rigid": scaled.tolist(), "nan": np.full((4, 4), np.nan).tolist()}


@pytest.mark.parametrize("what, message", [
    ("ragged", "must be a 4x4 list of numbers (metres)"), ("a string", "must be a 4x4 list of numbers (metres)"),
    ("3x3", "got shape (3, 3)"), ("a dict", "must be a 4x4 list of numbers"), ("not rigid", "not a rigid transform"),
    ("nan", "holds non-finite values")])
def test_damaged_tcp_pose_metadata_is_one_line(tmp_path, capsys, what, message):
    """A hand-edited or damaged tcp_pose gave a Python traceback (ValueError from numpy)."""
    model = sensor_preset("tmf8820")
    views = sensor_poses(6)
    frames = Simulator(PLANE.mesh(), model, SimSettings(rays_per_zone=16), seed=1).frames(views)
    tcp = views @ np.linalg.inv(X_TRUE)
    with CaptureWriter.create(tmp_path / "cap", model, hand_eye=X_TRUE) as w:
        for i in range(len(views)):
            meta = _damaged(tcp[i])[what] if i == 3 else tcp[i].tolist()
            w.append(Measurement(frames.hists[i], views[i], i, 0, frames.reference[i], {"tcp_pose": meta}))
        w.finish()
    assert main(["calibrate", "hand-eye", str(tmp_path / "cap"), "--plane", "0,0,0,0,0,1"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert "measurement 3: tcp_pose" in err and message in err, err
