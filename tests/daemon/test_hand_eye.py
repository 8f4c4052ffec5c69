"""Hand-eye calibration from a capture of a known target: a simulated capture taken with a known flange-to-sensor
transform X, recorded with a wrong one, gives X back; `spadscan calibrate hand-eye` prints it for the rig config."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest
import trimesh

from spadscan.cli import main
from spadscan.daemon.arm.pose_convert import check_pose, matrix_to_rotvec, rotvec_to_matrix
from spadscan.daemon.hand_eye import (SIGMA_FLOOR_BINS, UNCERTAIN_DEG, UNCERTAIN_MM, Target, _check_determined,
                                      fit_hand_eye, hand_eye_toml, parse_target, peak_bins, peak_positions)
from spadscan.daemon.scan_plan import invert_rigid
from spadscan.protocol import schedules
from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.errors import ConfigError
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, Simulator

X_TRUE = np.eye(4)
X_TRUE[:3, :3] = rotvec_to_matrix([0.03, -0.02, 0.05])
X_TRUE[:3, 3] = [0.012, -0.008, 0.047]


def looking_down(position, tilt_axis, tilt_rad, spin_rad) -> np.ndarray:
    """A sensor pose at `position` whose boresight points down, tilted about a horizontal axis and spun about it."""
    pose = np.eye(4)
    down = np.diag([1.0, -1.0, -1.0])
    pose[:3, :3] = rotvec_to_matrix(np.asarray(tilt_axis, float) * tilt_rad) @ down @ rotvec_to_matrix([0, 0, spin_rad])
    pose[:3, 3] = position
    return pose


def sensor_poses(n: int, seed: int = 0) -> np.ndarray:
    """Views of the table (z = 0) from 0.2-0.35 m, tilted up to 30 degrees in every direction and spun about the
    boresight: rotations about several axes, as the fit needs."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        az = 2 * math.pi * k / n
        axis = [math.cos(az), math.sin(az), 0.0]
        pos = [0.4 + 0.1 * rng.uniform(-1, 1), 0.1 * rng.uniform(-1, 1), rng.uniform(0.2, 0.35)]
        out.append(looking_down(pos, axis, math.radians(rng.uniform(5, 30)), rng.uniform(-math.pi, math.pi)))
    return np.array(out)


def make_capture(path, x_recorded: np.ndarray, n: int = 24, target: Target = Target("plane", (0, 0, 0)),
                 zero_bin_error: float = 0.0, true_sensor: np.ndarray | None = None,
                 x_true: np.ndarray = X_TRUE, frames_per_pose: int = 1, preset: str = "tmf8820",
                 tcp_pose: bool = True, range_noise_bins: float = 0.0) -> None:
    """Render the target at TCP x x_true, record the capture as if X were x_recorded (the daemon's way: sensor pose
    = actual TCP x the config's hand-eye, the TCP pose in each measurement's metadata). zero_bin_error: the unit's
    zero bin lies this many bins after the one the capture's sensor model states. true_sensor: the sensor's poses
    (default: `sensor_poses(n)`). frames_per_pose: frames taken at each pose (each its own noise). preset: the
    sensor's ('lcspc-sim': one zone, no reference histogram). tcp_pose: whether the metadata records it.
    range_noise_bins: each frame's zone histograms moved by a normal random shift of this spread (bins), every
    frame and zone its own, as a real return's position scatters beyond a simulated one's."""
    model = sensor_preset(preset)
    true_sensor = sensor_poses(n) if true_sensor is None else true_sensor
    n = len(true_sensor)
    tcp = true_sensor @ invert_rigid(x_true)
    unit = model.with_(zero_bin=model.zero_bin + zero_bin_error)
    sim = Simulator(target.mesh(), unit, SimSettings(rays_per_zone=256), seed=1)
    k = frames_per_pose
    frames = sim.frames(np.repeat(true_sensor, k, axis=0))
    hists = frames.hists
    if range_noise_bins:
        rng = np.random.default_rng(7)
        hists = hists.astype(np.float64)
        axis = np.arange(hists.shape[-1], dtype=np.float64)
        for h in hists.reshape(-1, hists.shape[-1]):
            h[:] = np.interp(axis - rng.normal(0.0, range_noise_bins), axis, h)
        hists = np.round(hists).astype(frames.hists.dtype)
    with CaptureWriter.create(path, model, hand_eye=x_recorded, chunk_size=64, frames_per_pose=k) as w:
        for j in range(n * k):
            i = j // k
            reference = None if frames.reference is None else frames.reference[j]
            meta = {"tcp_pose": tcp[i].tolist()} if tcp_pose else {}
            w.append(Measurement(hists[j], tcp[i] @ x_recorded, i, j % k, reference, meta))
        w.finish()


def wrong_x() -> np.ndarray:
    """X_TRUE off by 6 mm and 2.3 degrees, as a bracket's CAD value might be."""
    x = X_TRUE.copy()
    x[:3, :3] = X_TRUE[:3, :3] @ rotvec_to_matrix([0.03, 0.02, -0.01])
    x[:3, 3] += [0.004, -0.003, 0.0035]
    return x


def errors(x: np.ndarray) -> tuple[float, float]:
    """(mm, degrees) from X_TRUE."""
    return (float(np.linalg.norm(x[:3, 3] - X_TRUE[:3, 3]) * 1e3),
            math.degrees(float(np.linalg.norm(matrix_to_rotvec(X_TRUE[:3, :3].T @ x[:3, :3])))))


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    path = tmp_path_factory.mktemp("he") / "table"
    make_capture(path, wrong_x())
    return path


def test_the_fit_recovers_a_known_hand_eye_from_a_plane(capture):
    start_mm, start_deg = errors(wrong_x())
    fit = fit_hand_eye(capture, parse_target("0,0,0,0,0,1", None))
    mm, deg = errors(fit.hand_eye)
    assert start_mm > 5 and start_deg > 2
    assert mm < 1.0 and deg < 0.3, (mm, deg)
    assert fit.rms_mm < 0.3 * fit.rms_start_mm and fit.returns > 100 and fit.views == 24
    assert np.allclose(fit.start, wrong_x())


def test_the_printed_fit_says_how_certain_it_is(capture):
    fit = fit_hand_eye(capture, parse_target("0,0,0,0,0,1", None))
    assert 0.1 < max(fit.std_mm) < UNCERTAIN_MM and 0.05 < max(fit.std_deg) < UNCERTAIN_DEG and not fit.uncertain
    assert fit.lost == 0 and fit.returns == 216


def test_the_uncertainty_is_about_the_flanges_axes_on_a_bracket_that_turns_the_sensor(capture, tmp_path, capsys):
    """The same sensor poses on a bracket turned 90 degrees about the flange's x (an angled bracket): the flange's z
    is the sensor's y now, so both the translation's and the rotation's uncertainties along / about y and z swap.
    The rotation's did not (they were about the sensor's axes, labelled the flange's)."""
    turn = np.eye(4)
    turn[:3, :3] = rotvec_to_matrix([math.pi / 2, 0.0, 0.0])
    make_capture(tmp_path / "turned", turn @ wrong_x(), x_true=turn @ X_TRUE)
    plain = fit_hand_eye(capture, Target("plane", (0, 0, 0)))
    turned = fit_hand_eye(tmp_path / "turned", Target("plane", (0, 0, 0)))
    assert abs(plain.std_deg[1] - plain.std_deg[2]) > 0.2 * max(plain.std_deg[1:]), plain.std_deg
    swap = [0, 2, 1]
    assert np.allclose(turned.std_mm, np.array(plain.std_mm)[swap], rtol=0.05), (plain.std_mm, turned.std_mm)
    assert np.allclose(turned.std_deg, np.array(plain.std_deg)[swap], rtol=0.05), (plain.std_deg, turned.std_deg)
    assert main(["calibrate", "hand-eye", str(tmp_path / "turned"), "--plane", "0,0,0,0,0,1"]) == 0
    printed = [line for line in capsys.readouterr().out.splitlines() if line.startswith("uncertainty")][0]
    assert f"{turned.std_deg[1]:.2f}, {turned.std_deg[2]:.2f} deg" in printed
    assert "deg about the flange's x, y, z" in printed


def test_a_start_centimetres_off_along_the_boresight_comes_back(tmp_path):
    """The config's default identity while the sensor sits 47 mm out on its bracket (and 14 mm, 3.5 degrees off
    beside that): every predicted return lies outside the observed one's window. The fit landed 411 mm and 86 degrees
    away with a residual of 4 mm before it moved the start along the sensor's axis first. The start puts every
    return more than two bins off, outside its window: it has no residual there (it was scored as a 15 mm one)."""
    make_capture(tmp_path / "identity", np.eye(4))
    fit = fit_hand_eye(tmp_path / "identity", Target("plane", (0, 0, 0)))
    assert errors(np.eye(4))[0] > 45
    mm, deg = errors(fit.hand_eye)
    assert mm < 1.0 and deg < 0.3, (mm, deg)
    assert math.isnan(fit.rms_start_mm) and fit.lost_start == fit.returns == 216 and fit.rms_mm < 0.5
    assert fit.implausible() == []  # a bracket left out is a start the fit is meant to come back from


def test_the_fit_gains_nothing_by_losing_zones(capture):
    """A zone whose predicted return leaves the target costs more than any seen one: with a cost of 0 for it, a
    start 40 degrees off ended with 9 of its 216 zones lost. (From that far off the fit still ends in a wrong
    minimum: the docs ask for a start within about 20 degrees.)"""
    start = X_TRUE.copy()
    start[:3, :3] = X_TRUE[:3, :3] @ rotvec_to_matrix([0.5, 0.5, 0.0])
    fit = fit_hand_eye(capture, Target("plane", (0, 0, 0)), start=start)
    assert fit.lost == 0 and fit.returns == 216


@pytest.mark.parametrize("what", ["one ring", "two views", "straight down"])
def test_views_that_leave_the_hand_eye_undetermined_are_refused(tmp_path, what, capsys):
    """Views that differ only by a turn about one axis, or too few: the fit explained them to 0.1 mm with an X
    70-350 mm wrong and printed it."""
    rng = np.random.default_rng(0)
    if what == "one ring":
        views = schedules.elevation_rings(1, 12, 0.25, (0.45, 0.0, 0.0), 60, 60)
    elif what == "two views":
        views = np.array([looking_down([0.4, 0.0, 0.25], [math.cos(a), math.sin(a), 0], math.radians(20), a)
                          for a in (0.0, 2.0)])
    else:
        views = np.array([looking_down([0.4 + 0.1 * rng.uniform(-1, 1), 0.1 * rng.uniform(-1, 1),
                                        rng.uniform(0.2, 0.35)], [1, 0, 0], 0.0, rng.uniform(-math.pi, math.pi))
                          for _ in range(24)])
    make_capture(tmp_path / "cap", wrong_x(), true_sensor=views)
    assert main(["calibrate", "hand-eye", str(tmp_path / "cap"), "--plane", "0,0,0,0,0,1"]) == 1
    captured = capsys.readouterr()
    assert "hand_eye = " not in captured.out
    err = captured.err.strip()
    assert "\n" not in err and "the views do not determine the hand-eye transform" in err and "mm" in err, err


def test_a_part_the_views_say_nothing_of_is_called_wholly_undetermined():
    """An infinite spread read "+-inf mm", and a turn's spread of many revolutions "+-1.4e+04 deg", as if the
    program had failed; a finite spread keeps its number and unit. The Jacobian is diagonal: one standard deviation
    of each parameter is SIGMA_FLOOR_BINS over its column's value (rotations in rad, translations in m)."""
    sigma = SIGMA_FLOOR_BINS
    columns = [1e4, sigma / math.radians(400.0), sigma / math.radians(20.0),  # about x, y, z
               0.0, sigma / 0.040, 1e4]  # along x (the views say nothing of it), y, z
    with pytest.raises(ConfigError) as info:
        _check_determined(np.diag(columns), "cap")
    assert str(info.value).startswith(
        "cap: the views do not determine the hand-eye transform (along x wholly undetermined, along y +-40 mm, "
        "about y wholly undetermined, about z +-20 deg in the flange frame): "), str(info.value)
    assert "inf" not in str(info.value) and "nan" not in str(info.value)


def test_the_zero_bin_can_be_fitted_with_the_hand_eye(tmp_path):
    """A unit whose zero bin is half a bin (6.8 mm) later than its model says: fitted alone, X takes the offset
    along the boresight; fitted with the zero bin, both come back."""
    make_capture(tmp_path / "late", wrong_x(), zero_bin_error=0.5)
    target = Target("plane", (0, 0, 0))
    alone = fit_hand_eye(tmp_path / "late", target)
    both = fit_hand_eye(tmp_path / "late", target, fit_zero_bin=True)
    assert errors(alone.hand_eye)[0] > 4.0
    assert errors(both.hand_eye)[0] < 1.5 and both.zero_bin_shift == pytest.approx(0.5, abs=0.12)
    assert both.rms_mm < alone.rms_mm


def test_a_sphere_gives_the_hand_eye_too(tmp_path):
    """Views of a 10 cm ball from around it, aimed beside its centre: its edge crosses the zones (views aimed at the
    centre see the same range wherever the sensor shifts sideways)."""
    target = Target("sphere", (0.45, 0.0, 0.1), radius=0.1)
    rng = np.random.default_rng(2)
    poses = []
    for k in range(20):
        d = rng.normal(size=3)
        d[2] = abs(d[2]) + 0.5
        d /= np.linalg.norm(d)
        eye = np.array(target.point) + 0.3 * d
        aim = np.array(target.point) + rng.uniform(-0.07, 0.07, 3)
        z = (aim - eye) / np.linalg.norm(aim - eye)
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1) @ rotvec_to_matrix([0, 0, rng.uniform(-3, 3)])
        pose[:3, 3] = eye
        poses.append(pose)
    model = sensor_preset("tmf8820")
    sim = Simulator(target.mesh(), model, SimSettings(rays_per_zone=256), seed=3)
    frames = sim.frames(np.array(poses))
    tcp = np.array(poses) @ invert_rigid(X_TRUE)
    with CaptureWriter.create(tmp_path / "ball", sim.sensor, hand_eye=wrong_x()) as w:
        for i, t in enumerate(tcp):
            w.append(Measurement(frames.hists[i], t @ wrong_x(), i, 0, frames.reference[i], {"tcp_pose": t.tolist()}))
        w.finish()
    mm, deg = errors(fit_hand_eye(tmp_path / "ball", target).hand_eye)
    assert mm < 1.0 and deg < 0.5, (mm, deg)


def test_the_peak_estimator_reads_a_pulse_where_it_is_and_refuses_noise():
    model = sensor_preset("tmf8820")
    kernel, origin = model.pulse.kernel(1)
    h = np.full((3, 128), 20.0)
    h[0, 40 - origin: 40 - origin + kernel.size] += 5000 * kernel
    h[1, 60] += 3000
    h[2, 70] += 15  # not 6 sigma above a background of 20
    pos = peak_positions(h, peak_bins(h, 16))
    assert 40.3 < pos[0] < 41.6 and pos[1] == pytest.approx(60.5) and np.isnan(pos[2])


@pytest.mark.parametrize("plane, sphere, message", [
    (None, None, "give the target"),
    ("0,0,0,0,0,1", "0,0,0,1", "not both"),
    ("0,0,0,0,1", None, "--plane '0,0,0,0,1' must be 6 numbers X,Y,Z,NX,NY,NZ"),
    ("0,0,0,0,0,0", None, "the normal (NX, NY, NZ) must not be zero"),
    (None, "0,0,0,-1", "the radius -1 m must be in (0, 2]"),
    (None, "a,b,c,d", "--sphere 'a,b,c,d' must be 4 numbers"),
])
def test_a_bad_target_is_one_line(plane, sphere, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_target(plane, sphere)


def test_spadscan_calibrate_hand_eye_prints_the_config_line(capture, capsys):
    assert main(["calibrate", "hand-eye", str(capture), "--plane", "0,0,0,0,0,1"]) == 0
    out, err = capsys.readouterr()
    assert "warning" not in err, err
    assert "24 views" in out and "mm fitted" in out and "hand_eye = [[" in out
    line = out[out.index("hand_eye = "):]
    x = np.array(tomllib.loads(line)["hand_eye"])
    assert errors(x)[0] < 1.0
    assert main(["calibrate", "hand-eye", str(capture)]) == 1
    assert "give the target" in capsys.readouterr().err
    assert main(["calibrate", "hand-eye", str(capture.parent / "nope"), "--plane", "0,0,0,0,0,1"]) == 1
    assert "no such capture folder" in capsys.readouterr().err


def test_calibrate_counts_views_as_poses_and_says_its_returns_count_frames(tmp_path, capsys):
    """A capture of 24 poses x 3 frames has 24 views (a reconstruction sums each pose's frames into one), not 72;
    the zone returns are counted per frame, and the line says so."""
    path = tmp_path / "three"
    make_capture(path, X_TRUE, frames_per_pose=3)
    assert main(["calibrate", "hand-eye", str(path), "--plane", "0,0,0,0,0,1"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    fit = fit_hand_eye(path, Target("plane", (0, 0, 0)))
    assert fit.views == 24 and fit.frames == 72 and fit.returns + fit.lost > 72, fit
    off = f" ({fit.lost} more off it at the fitted hand_eye, left out)" if fit.lost else ""
    assert first == f"{path}: 24 views (72 frames), {fit.returns} zone returns on the plane in those 72 frames{off}"


class _BoxOnTable:
    """The table with a 12 cm box standing under the views: not the bare plane the fit is told of."""

    def mesh(self):
        box = trimesh.creation.box([0.25, 0.25, 0.12])
        box.apply_translation([0.4, 0.0, 0.06])
        return trimesh.util.concatenate([Target("plane", (0, 0, 0)).mesh(), box])


def test_a_fit_far_beyond_a_bracket_correction_is_warned_about(tmp_path, capsys):
    """Something standing on the plane: the fit pulled X 12 cm along the sensor's axis and printed it for the config
    with no more than the advice to add views (on a real capture, a fit 21 cm and 52 deg off came with a tight
    uncertainty and no warning at all). A start 40 degrees off ends 37 deg and 20 cm from it."""
    make_capture(tmp_path / "box", wrong_x(), target=_BoxOnTable())
    assert main(["calibrate", "hand-eye", str(tmp_path / "box"), "--plane", "0,0,0,0,0,1"]) == 0
    captured = capsys.readouterr()
    assert "hand_eye = [[" in captured.out
    warning = [line for line in captured.err.splitlines() if "warning: implausible fit" in line]
    assert len(warning) == 1 and "mm along its axis" in warning[0], captured.err
    assert all(cause in warning[0] for cause in ("wrong target", "standing on the plane", "a sign")), warning[0]
    start = X_TRUE.copy()
    start[:3, :3] = X_TRUE[:3, :3] @ rotvec_to_matrix([0.5, 0.5, 0.0])
    make_capture(tmp_path / "far", start)
    assert any("tilted the sensor's axis" in odd for odd in fit_hand_eye(tmp_path / "far", Target("plane", (0, 0, 0)))
               .implausible())


def test_a_target_that_is_not_there_is_one_line(capture, capsys):
    assert main(["calibrate", "hand-eye", str(capture), "--plane", "0,0,2,0,0,1"]) == 1
    assert "zone returns see the target where it was said to be" in capsys.readouterr().err


def test_the_printed_line_gives_a_config_whose_targets_the_arm_accepts():
    """Printed to six decimals, one fitted X in four planned targets the UR arm would refuse (not orthonormal to
    1e-6): the line carries nine."""
    rng = np.random.default_rng(1)
    for _ in range(50):
        x = np.eye(4)
        x[:3, :3] = rotvec_to_matrix(rng.normal(size=3) * 0.6)
        x[:3, 3] = rng.uniform(-0.05, 0.05, 3)
        printed = np.array(tomllib.loads(hand_eye_toml(x))["hand_eye"])
        check_pose(printed)
        assert np.abs(printed - x).max() < 1e-9
