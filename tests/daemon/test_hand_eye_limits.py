"""The numbers `spadscan calibrate hand-eye` states hold where they bind: the uncertainty is the spread of the fitted
X (a known mount recovered within it, the textbook least-squares spread, its rotations about the flange's axes, the
floor on the scatter), and each warning limit fires just past its value and not just inside."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spadscan.daemon.arm.pose_convert import matrix_to_rotvec, rotvec_to_matrix
from spadscan.daemon.hand_eye import (HEIGHT_ACROSS, MIN_SNR, PLAUSIBLE_ACROSS_MM, PLAUSIBLE_ALONG_MM,
                                      PLAUSIBLE_ALONG_UNMOUNTED_MM, PLAUSIBLE_LOST, PLAUSIBLE_RMS_MM,
                                      PLAUSIBLE_TILT_DEG, SIGMA_FLOOR_BINS, HandEyeFit, Target, _compose,
                                      _flange_rotation, _jacobian, _left_jacobian, _rms_mm, _uncertainty,
                                      capture_tcp_poses, fit_hand_eye, peak_bins, peak_positions)
from spadscan.daemon.scan_plan import invert_rigid
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.sensor_presets import sensor_preset
from test_hand_eye import X_TRUE, make_capture, sensor_poses, wrong_x

PLANE = Target("plane", (0, 0, 0))


def _z_scores(fit: HandEyeFit) -> np.ndarray:
    """The fitted X's error from X_TRUE in its stated standard deviations: along the flange's x, y, z, then about
    them."""
    along = (fit.hand_eye[:3, 3] - X_TRUE[:3, 3]) * 1e3
    about = np.degrees(matrix_to_rotvec(fit.hand_eye[:3, :3] @ X_TRUE[:3, :3].T))  # a turn in the flange frame
    return np.concatenate([along / fit.std_mm, about / fit.std_deg])


@pytest.fixture(scope="module")
def fits(tmp_path_factory):
    """The table from 24 views, as simulated (residuals far below SIGMA_FLOOR_BINS) and with every zone's return
    moved by 0.4 bins of random scatter."""
    out = {}
    for noise in (0.0, 0.4):
        path = tmp_path_factory.mktemp("limits") / f"noise{noise}"
        make_capture(path, wrong_x(), range_noise_bins=noise)
        out[noise] = fit_hand_eye(path, PLANE)
    return out


def test_a_known_mount_is_recovered_within_its_stated_uncertainty(fits):
    """Each part of X lies within three of its stated standard deviations of the mount the capture was taken
    with, whether the scatter of the returns or the floor sets the uncertainty."""
    for noise, fit in fits.items():
        z = _z_scores(fit)
        assert np.all(np.abs(z) < 3.5), (noise, z)
    assert np.sum(_z_scores(fits[0.4]) ** 2) > 0.5  # the noisy fit's error is not hidden under a wide spread


def test_the_uncertainty_grows_with_the_scatter_above_its_floor(fits):
    """Returns scattered well above SIGMA_FLOOR_BINS widen the uncertainty in proportion; below it, the floor
    holds (a simulated capture's residuals, 0.006 bins, would have claimed X to a few hundredths of a millimetre)."""
    clean, noisy = fits[0.0], fits[0.4]
    assert clean.rms_mm / clean.bin_width_mm < 0.2 * SIGMA_FLOOR_BINS
    assert max(clean.std_mm) > 0.5 and max(clean.std_deg) > 0.3, (clean.std_mm, clean.std_deg)
    ratio = noisy.rms_mm / noisy.bin_width_mm / SIGMA_FLOOR_BINS
    assert ratio > 1.8, ratio
    assert np.allclose(np.array(noisy.std_mm) / clean.std_mm, ratio, rtol=0.15), (noisy.std_mm, clean.std_mm, ratio)
    assert np.allclose(np.array(noisy.std_deg) / clean.std_deg, ratio, rtol=0.15), (noisy.std_deg, ratio)


@pytest.mark.parametrize("n_rot, n_params", [(3, 6), (3, 7), (2, 5)])
def test_the_uncertainty_is_the_spread_of_least_squares_estimates(n_rot, n_params):
    """For a linear model with correlated parameters (radians beside metres), the stated standard deviations match
    the spread of least-squares estimates over many draws of the returns' scatter."""
    rng = np.random.default_rng(3)
    mix = np.eye(n_params) + 0.6 * rng.normal(size=(n_params, n_params))
    jac = rng.normal(size=(60, n_params)) @ mix * np.array([30.0] * n_rot + [800.0] * 3 + [1.0] * (n_params - n_rot
                                                                                                   - 3))
    sigma = 0.25
    draws = rng.normal(0.0, sigma, size=(60, 20000))
    estimates = np.linalg.lstsq(jac, draws, rcond=None)[0]
    spread = estimates.std(axis=1)
    std_mm, std_deg = _uncertainty(jac, sigma, n_rot)
    assert len(std_deg) == n_rot
    assert np.allclose(std_mm, spread[n_rot:n_rot + 3] * 1e3, rtol=0.03), (std_mm, spread)
    assert np.allclose(std_deg, np.degrees(spread[:n_rot]), rtol=0.03), (std_deg, spread)


def test_the_rotation_columns_are_turns_about_the_flanges_axes():
    """Far from the start (a rotation of 1.1 rad: the left Jacobian matters) on a bracket turned off every axis, a
    column of the converted Jacobian is the change of the residuals for a small turn of the fitted X about that
    axis of the flange (the sensor's axes, or the transposed or uninverted map, give other columns)."""
    start = np.eye(4)
    start[:3, :3] = rotvec_to_matrix([0.7, -0.4, 1.1])
    start[:3, 3] = [0.01, -0.02, 0.05]
    params = np.array([0.6, 0.3, -0.8, 0.001, 0.002, -0.003])
    probe = np.random.default_rng(4).normal(size=(5, 12))

    def residual_of(x: np.ndarray) -> np.ndarray:
        return probe @ np.concatenate([x[:3, :3].ravel(), x[:3, 3]])

    def residual(p: np.ndarray) -> np.ndarray:
        return residual_of(_compose(start, p))

    steps = np.full(6, 1e-6)
    jac = _flange_rotation(_jacobian(residual, params, residual(params), steps), start, params)
    fitted = _compose(start, params)
    h = 1e-6

    def turned(w: np.ndarray) -> np.ndarray:
        """The fitted X turned by w about the flange's axes, its translation (a parameter of its own) kept."""
        out = fitted.copy()
        out[:3, :3] = rotvec_to_matrix(w) @ fitted[:3, :3]
        return out

    for axis in range(3):
        expected = (residual_of(turned(np.eye(3)[axis] * h)) - residual_of(turned(-np.eye(3)[axis] * h))) / (2 * h)
        assert np.allclose(jac[:, axis], expected, rtol=1e-3, atol=1e-4), (axis, jac[:, axis], expected)


@pytest.mark.parametrize("size", [3e-5, 0.5, 2.5])
def test_the_left_jacobian_is_the_rotations_derivative(size):
    """R(r + dr) = R(J dr) R(r) to first order, near zero (its series) and far from it (its closed form)."""
    r = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]) * size
    h = 1e-6
    numeric = np.stack([(matrix_to_rotvec(rotvec_to_matrix(r + h * e) @ rotvec_to_matrix(r).T)
                         - matrix_to_rotvec(rotvec_to_matrix(r - h * e) @ rotvec_to_matrix(r).T)) / (2 * h)
                        for e in np.eye(3)], axis=1)
    assert np.allclose(_left_jacobian(r), numeric, atol=1e-8), (_left_jacobian(r), numeric)


def test_the_residual_rms_is_in_millimetres_of_range():
    model = sensor_preset("tmf8820")
    width_mm = model.bin_width_m * 1e3
    assert _rms_mm(np.array([1.0, -1.0, 1.0, -1.0]), model) == pytest.approx(width_mm)
    assert _rms_mm(np.array([3.0, 4.0]), model) == pytest.approx(math.sqrt(12.5) * width_mm)
    assert math.isnan(_rms_mm(np.array([]), model))


def test_without_recorded_tcp_poses_the_arms_poses_come_from_the_stored_ones(tmp_path):
    """A capture without tcp_pose metadata (an older daemon): the TCP is the stored sensor pose times the inverse of
    the X it was taken with, and the fit recovers X from it as well."""
    make_capture(tmp_path / "old", wrong_x(), tcp_pose=False)
    reader = CaptureReader(tmp_path / "old")
    tcp = capture_tcp_poses(reader, reader.load())
    assert np.allclose(tcp, sensor_poses(24) @ invert_rigid(X_TRUE), atol=1e-9)
    assert np.all(np.abs(_z_scores(fit_hand_eye(tmp_path / "old", PLANE))) < 3.5)


def _fit(moved_mm=(0.0, 0.0, 0.0), tilt_deg: float = 0.0, rms_mm: float = 1.0, lost: int = 0,
         kind: str = "plane", mounted: bool = True) -> HandEyeFit:
    """A fit that moved X from a start (looking along the flange's z, on a bracket unless not `mounted`) by
    moved_mm (along the flange's x, y, z: z is the sensor's axis) and tilted the sensor's axis by tilt_deg about
    the flange's x, with 100 zone returns shown."""
    start = np.eye(4)
    start[:3, 3] = [0.0, 0.0, 0.05] if mounted else 0.0
    x = _compose(start, np.array([math.radians(tilt_deg), 0.0, 0.0, *np.array(moved_mm) / 1e3]))
    return HandEyeFit(x, start, 1.0, rms_mm, 100 - lost, 24, lost=lost, kind=kind)


LIMITS = [
    ("tilted the sensor's axis", dict(tilt_deg=PLAUSIBLE_TILT_DEG - 0.1), dict(tilt_deg=PLAUSIBLE_TILT_DEG + 0.1)),
    ("mm across its axis", dict(moved_mm=(PLAUSIBLE_ACROSS_MM - 0.1, 0, 0)),
     dict(moved_mm=(0, PLAUSIBLE_ACROSS_MM + 0.1, 0))),
    ("mm along its axis", dict(moved_mm=(0, 0, PLAUSIBLE_ALONG_MM - 0.1)),
     dict(moved_mm=(0, 0, -PLAUSIBLE_ALONG_MM - 0.1))),
    ("mm along its axis", dict(moved_mm=(0, 0, PLAUSIBLE_ALONG_UNMOUNTED_MM - 0.1), mounted=False),
     dict(moved_mm=(0, 0, PLAUSIBLE_ALONG_UNMOUNTED_MM + 0.1), mounted=False)),
    ("residual RMS", dict(rms_mm=PLAUSIBLE_RMS_MM - 0.01), dict(rms_mm=PLAUSIBLE_RMS_MM + 0.01)),
    ("off the plane", dict(lost=int(PLAUSIBLE_LOST * 100)), dict(lost=int(PLAUSIBLE_LOST * 100) + 1)),
]


@pytest.mark.parametrize("phrase, inside, past", LIMITS, ids=[f"{p}-{i}" for i, (p, *_) in enumerate(LIMITS)])
def test_each_implausible_limit_fires_just_past_it_and_not_inside(phrase, inside, past):
    assert _fit(**inside).implausible() == []
    odd = _fit(**past).implausible()
    assert len(odd) == 1 and phrase in odd[0], odd


def test_returns_off_a_sphere_are_not_warned_about():
    """Beside a sphere, zones that see the wall behind are expected."""
    assert _fit(lost=60, kind="sphere").implausible() == []


HEIGHT = "likely the target's height"


@pytest.mark.parametrize("changes, height", [
    ({}, True),
    (dict(moved_mm=(HEIGHT_ACROSS * 100 + 0.2, 0, 100)), False),
    (dict(moved_mm=(0, PLAUSIBLE_ACROSS_MM - 0.1, PLAUSIBLE_ALONG_MM + 0.1)), True),
    (dict(moved_mm=(0, PLAUSIBLE_ACROSS_MM + 0.1, PLAUSIBLE_ALONG_MM + 0.1)), False),
    (dict(tilt_deg=PLAUSIBLE_TILT_DEG - 0.1), True),
    (dict(tilt_deg=PLAUSIBLE_TILT_DEG + 0.1), False),
    (dict(rms_mm=PLAUSIBLE_RMS_MM - 0.01), True),
    (dict(rms_mm=PLAUSIBLE_RMS_MM + 0.01), False),
    (dict(moved_mm=(0, 0, PLAUSIBLE_ALONG_MM - 0.1)), False),
])
def test_a_move_along_the_axis_is_put_down_to_the_targets_height_within_its_limits(changes, height):
    """A fit moved 100 mm along the sensor's axis and up to HEIGHT_ACROSS of that across it, tilting the axis no more
    than PLAUSIBLE_TILT_DEG and explaining the returns within PLAUSIBLE_RMS_MM, blames the height first; one just
    past any of these does not (within the along limit nothing is implausible, and nothing is blamed)."""
    args = dict(moved_mm=(HEIGHT_ACROSS * 100 - 0.2, 0, 100))
    args.update(changes)
    fit = _fit(**args)
    if not fit.implausible():
        assert not height
        return
    assert fit.likely_causes().startswith(HEIGHT) == height, (args, fit.likely_causes())


@pytest.mark.parametrize("above, kept", [(6.0 * 10.0 - 0.1, False), (6.0 * 10.0, True), (6.0 * 10.0 + 0.1, True)])
def test_a_peak_counts_from_min_snr_poisson_sigmas_above_the_background(above, kept):
    """A background of 99 counts: one Poisson sigma of it (and the one count added for an empty histogram) is 10, so
    a peak counts from MIN_SNR x 10 counts above it."""
    assert MIN_SNR == 6.0
    h = np.full((1, 64), 99.0)
    h[0, 30] += above
    assert np.isfinite(peak_positions(h, peak_bins(h, 8))[0]) == kept


def test_scatter_that_a_poses_frames_average_out_is_not_counted_as_its_error(fits, tmp_path):
    """Four frames a pose, each zone's return scattered 0.8 bins in every frame on its own (as photon noise is):
    the pose's mean scatters about 0.4 bins, and X is as certain as from one frame scattered 0.4 bins. The scatter
    of single frames (twice that) is not the poses'. One of the 864 returns lay on its window's edge, where a
    difference step lost it: its jump made the turn about z look known to 0.17 deg (1.4 from one frame)."""
    make_capture(tmp_path / "four", wrong_x(), frames_per_pose=4, range_noise_bins=0.8)
    four = fit_hand_eye(tmp_path / "four", PLANE)
    one = fits[0.4]
    assert four.rms_mm > 1.6 * one.rms_mm, (four.rms_mm, one.rms_mm)  # single frames: twice the scatter
    assert np.allclose(four.std_mm, one.std_mm, rtol=0.25), (four.std_mm, one.std_mm)
    assert np.allclose(four.std_deg, one.std_deg, rtol=0.25), (four.std_deg, one.std_deg)
