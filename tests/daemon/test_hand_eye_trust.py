"""What `spadscan calibrate hand-eye` says about its own fit can be trusted: a start turned about the sensor's axis
comes back, a plane given at the wrong height is warned about by name, a zone whose predicted return misses the
observed one is counted as lost (not as a match) before and after the fit, and damaged tcp_pose metadata is one line."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spadscan.cli import main
from spadscan.daemon.arm.pose_convert import matrix_to_rotvec, rotvec_to_matrix
from spadscan.daemon.hand_eye import (MIN_RANGE_M, WINDOW_BINS, Target, _Predictor, capture_tcp_poses, fit_hand_eye,
                                      peak_bins, peak_positions)
from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.errors import ConfigError
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, Simulator
from test_hand_eye import X_TRUE, _BoxOnTable, errors, looking_down, make_capture, sensor_poses, wrong_x

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
    # The start's residuals are the capture's X's, not those of the turn the fit went on from.
    assert fit.rms_start_mm > 5.0 and fit.lost_start > 20, (fit.rms_start_mm, fit.lost_start)
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


def _config_keys() -> set[str]:
    """Every key a rig config can hold: the tables', every backend's own, the top level's."""
    from spadscan.daemon.backends import ARM_BACKENDS, SENSOR_BACKENDS
    from spadscan.daemon.config import TABLES, DaemonConfig
    from spadscan.daemon.config_keys import key_names

    classes = [DaemonConfig, *TABLES.values(), *ARM_BACKENDS.values(), *SENSOR_BACKENDS.values()]
    return {name for cls in classes for name in key_names(cls)}


def test_a_fitted_zero_bin_is_said_to_be_needed_by_the_printed_hand_eye(tmp_path, capsys):
    """A unit half a bin late, fitted with --fit-zero-bin: the printed X is right only with the fitted shift, which
    nothing applies (the daemon stores its preset's zero bin, the worker reads ranges with it), so every range stays
    about 7 mm off; the output gave the shift as a bare number and put the X in the config snippet as if it were
    enough on its own."""
    assert not any("zero" in name for name in _config_keys())  # else the warning must name the key to set
    make_capture(tmp_path / "late", wrong_x(), zero_bin_error=0.5)
    assert main(["calibrate", "hand-eye", str(tmp_path / "late"), "--plane", "0,0,0,0,0,1", "--fit-zero-bin"]) == 0
    out, err = capsys.readouterr()
    fit = fit_hand_eye(tmp_path / "late", PLANE, fit_zero_bin=True)
    shift_mm = fit.zero_bin_shift * fit.bin_width_mm
    assert 0.4 < fit.zero_bin_shift < 0.6 and 5.4 < shift_mm < 8.2, fit.zero_bin_shift
    lines = warnings(err)
    assert len(lines) == 1, err
    assert (f"right only with the sensor's zero bin moved {fit.zero_bin_shift:+.3f} bins ({shift_mm:+.1f} mm of "
            f"range)") in lines[0], lines[0]
    assert "no config key sets the zero bin" in lines[0] and "the daemon and the worker do not apply" in lines[0]
    assert f"every range stays {shift_mm:.1f} mm off" in lines[0] and "without --fit-zero-bin" in lines[0]
    assert "hand_eye = [[" in out
    assert main(["calibrate", "hand-eye", str(tmp_path / "late"), "--plane", "0,0,0,0,0,1"]) == 0
    assert "zero bin" not in capsys.readouterr().err  # without the flag X takes the shift: nothing to apply


def test_more_frames_at_the_same_poses_do_not_make_the_hand_eye_more_certain(tmp_path):
    """Frames at one pose share its error (the arm's repeatability, the target's placement): counted as independent
    returns, 4 frames at the same 6 poses halved the stated uncertainty (2.38 -> 1.19 mm, 1.32 -> 0.66 deg)."""
    fits = {}
    for k in (1, 4):
        make_capture(tmp_path / f"f{k}", wrong_x(), n=6, frames_per_pose=k)
        fits[k] = fit_hand_eye(tmp_path / f"f{k}", PLANE)
    assert fits[4].returns == 4 * fits[1].returns
    assert np.allclose(fits[4].std_mm, fits[1].std_mm, rtol=0.1), (fits[1].std_mm, fits[4].std_mm)
    assert np.allclose(fits[4].std_deg, fits[1].std_deg, rtol=0.1), (fits[1].std_deg, fits[4].std_deg)


@pytest.mark.parametrize("frames", [1, 4])
def test_more_frames_do_not_pass_views_that_leave_the_hand_eye_undetermined(tmp_path, capsys, frames):
    """Four views leave X +-10.4 mm along y: refused with one frame a pose, printed with four (+-5.2 mm)."""
    make_capture(tmp_path / "four", wrong_x(), true_sensor=sensor_poses(4), frames_per_pose=frames)
    assert main(["calibrate", "hand-eye", str(tmp_path / "four"), "--plane", "0,0,0,0,0,1"]) == 1
    err = capsys.readouterr().err.strip()
    assert "the views do not determine the hand-eye transform (along y +-10" in err, err


@pytest.mark.parametrize("views, frames, fit_zero_bin, refused", [
    (9, 1, False, True), (10, 1, False, False), (9, 3, False, True), (11, 1, True, True), (12, 1, True, False)])
def test_a_fit_needs_two_zone_returns_a_view_per_parameter(tmp_path, views, frames, fit_zero_bin, refused):
    """A one-zone sensor: one return a view. Five parameters (the turn about its axis is held) need ten views, six
    (a zero bin too) twelve; a pose's frames are not more views (nine views of three frames passed as 27)."""
    make_capture(tmp_path / "one", X_TRUE, true_sensor=sensor_poses(views), frames_per_pose=frames,
                 preset="lcspc-sim")  # from the right X every view's return lies in its window
    try:
        fit_hand_eye(tmp_path / "one", PLANE, fit_zero_bin=fit_zero_bin)
        message = ""
    except ConfigError as exc:
        message = str(exc)
    need = 12 if fit_zero_bin else 10
    assert (f"only {views} zone returns see the target where it was said to be (need {need}," in message) == refused, \
        message


def test_a_one_zone_sensor_leaves_the_turn_about_its_axis_undetermined(tmp_path, capsys):
    """One zone sees the same at every turn about the sensor's axis: the fit went on from the start turned 90 deg
    (asking about a connector), ended 71 deg off about the axis and reported that turn as known to 0.05 deg."""
    make_capture(tmp_path / "one", wrong_x(), preset="lcspc-sim")
    fit = fit_hand_eye(tmp_path / "one", PLANE)
    assert not fit.turn_determined and fit.turn_deg == 0 and len(fit.std_deg) == 2
    kept = matrix_to_rotvec(fit.start[:3, :3].T @ fit.hand_eye[:3, :3])
    assert abs(kept[2]) < 1e-9, kept  # the turn about the sensor's axis is the start's
    mm, deg = errors(fit.hand_eye)
    assert mm < 3 * max(fit.std_mm) and fit.implausible() == [], (mm, fit.std_mm)
    assert main(["calibrate", "hand-eye", str(tmp_path / "one"), "--plane", "0,0,0,0,0,1"]) == 0
    out = capsys.readouterr().out
    line = [row for row in out.splitlines() if row.startswith("uncertainty")][0]
    assert "about the flange's x, y, z" not in line and "the turn about the sensor's axis: not determined" in line
    assert "deg tilt of the sensor's axis about its own x, y" in line
    snippet = out[out.index("for the rig config's [arm] table:"):].splitlines()
    assert snippet[1].startswith("# the turn about the sensor's axis is the capture's hand_eye's, not fitted")
    assert "turned" not in out


def test_a_one_zone_capture_that_leaves_its_axis_tilt_undetermined_is_refused(tmp_path, capsys):
    """The held turn does not count as determined, nor does it hide the tilts: views all straight down refuse."""
    rng = np.random.default_rng(0)
    views = np.array([looking_down([0.4 + 0.1 * rng.uniform(-1, 1), 0.1 * rng.uniform(-1, 1),
                                    rng.uniform(0.2, 0.35)], [1, 0, 0], 0.0, rng.uniform(-math.pi, math.pi))
                      for _ in range(24)])
    make_capture(tmp_path / "down", wrong_x(), true_sensor=views, preset="lcspc-sim")
    assert main(["calibrate", "hand-eye", str(tmp_path / "down"), "--plane", "0,0,0,0,0,1"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "the views do not determine the hand-eye transform" in err, err
    assert "about z" not in err
