"""Hand-eye calibration: the flange-to-sensor transform X ([arm] hand_eye) fitted from a capture of a known target.

Every measurement of a daemon capture records the arm's actual TCP pose T (metadata `tcp_pose`; otherwise the
stored sensor pose times the inverse of the stored X). With the right X the sensor sat at T x X, and a known target
(a plane: the table; or a sphere) seen from there gives histograms whose first return lies where the sensor model
puts it. The fit moves X until, for every view and zone, the *observed* return's position (a windowed centroid
around the histogram's peak, in bins) matches the *predicted* one: the same estimator applied to the histogram the
simulator expects for that zone (`protocol.simulator`: the zone's rays, the pulse, gains, crosstalk, pile-up), so
the estimator's own biases cancel. Levenberg-Marquardt over six parameters (a rotation vector applied on the sensor's
side of X's rotation, a translation in the flange frame), optionally a seventh: a shift of the sensor model's zero
bin; before it, the start is moved along the sensor's axis to the returns' median range (a start centimetres off along
it leaves the fit no way back). After it, X's uncertainty (sigma^2 (J^T J)^-1); views that leave part of X
undetermined are refused rather than fitted. Both uncertainties are given along and about the flange's axes.

A plane constrains X well when the views tilt the tool in different directions (rotations about several axes carry
X's translation across the plane's normal); residuals of a few millimetres remain on real data (the peak's sub-bin
position, the scatter of real signals). Units: metres, radians; residuals in millimetres of one-way range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import CaptureError, ConfigError
from spadscan.protocol.sensor_model import SensorModel
from spadscan.protocol.simulator import BACKGROUND_FLOOR, SimSettings, Simulator

from .arm.pose_convert import matrix_to_rotvec, rotvec_to_matrix
from .scan_plan import invert_rigid

WINDOW_BINS = 2
"""The peak estimator averages bin centres over the peak bin and this many bins either side, above background."""
MIN_RANGE_M = 0.05
"""Returns nearer than this are not looked for (the sensor's own zero-range crosstalk sits there)."""
MIN_SNR = 6.0
"""A zone's return counts when its peak stands this many Poisson sigmas above the histogram's median."""
MIN_SIGNAL_COUNTS = 1.0
"""A zone is expected to see the target when the target's signal adds at least this many counts to its histogram."""
LOST_ZONE_BINS = 2 * WINDOW_BINS + 1
"""The residual (bins) of a zone whose predicted return left the target or its window: more than any seen zone's
(both positions lie within the same window of 2 * WINDOW_BINS + 1 bins)."""
RAYS_PER_ZONE = 64
"""Rays per zone of the predicted histograms (a fixed, deterministic set: the fit sees a smooth function)."""
PLANE_HALF_SIZE_M = 3.0
"""Half the side of the square that stands for an infinite plane."""
SIGMA_FLOOR_BINS = 0.1
"""The least scatter of a return's position (bins) the uncertainty assumes: a simulated capture's residuals are
far below real ones (0.1-0.3 bins), and a fit to noise-free data is no more certain than the sensor."""
UNDETERMINED_MM = 10.0
UNDETERMINED_DEG = 5.0
"""A fit is refused when, for returns scattered by SIGMA_FLOOR_BINS, one standard deviation of X's translation along
a flange axis or of its rotation about one exceeds these: the views leave that part of X to the optimiser's drift
(views all turned about one axis, rings without jitter, too few views: tens of millimetres to metres); views tilted
5-30 degrees every way give about 1 mm and 0.6 degrees."""
UNCERTAIN_MM = 5.0
UNCERTAIN_DEG = 2.0
"""Above these (one standard deviation, for the fit's own scatter) `calibrate` warns: the recipe in the docs gives
about 2.5 mm and 0.7 degrees for returns scattered by SIGMA_FLOOR_BINS."""

PLAUSIBLE_TILT_DEG = 10.0
PLAUSIBLE_ACROSS_MM = 20.0
PLAUSIBLE_ALONG_MM = 100.0
PLAUSIBLE_RMS_MM = 10.0
"""Beyond these `calibrate` warns that the fit is more likely wrong than the bracket: a bracket's drawing or a
caliper measurement puts the sensor's axis within a few degrees and its aperture within a few millimetres sideways,
and a start whose axis is tilted more than about 20 degrees can settle in a wrong minimum (firmware_notes/hand_eye.md),
so a fitted tilt of the axis over 10 degrees or a sideways shift over 20 mm is twice a careless start. Along the
axis the start may be centimetres off (the default identity, a bracket left out: the fit moves it back first), but
not more than a bracket is long (10 cm). A turn about the axis is not limited (the connector's orientation may be
unknown; the fit recovers any). A residual RMS over 10 mm is more than real data leaves with the right target (a
few millimetres): tens of millimetres mean a wrong target."""


@dataclass(frozen=True)
class Target:
    """A known calibration object in the base frame: kind 'plane' (point, unit normal) or 'sphere' (centre,
    radius), metres."""

    kind: str
    point: tuple[float, float, float]
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    radius: float = 0.0

    def mesh(self):
        """A mesh of the target for the simulator: a square 6 m across for a plane, a fine icosphere for a sphere."""
        import trimesh

        if self.kind == "sphere":
            mesh = trimesh.creation.icosphere(subdivisions=5, radius=self.radius)
            mesh.apply_translation(self.point)
            return mesh
        n = np.asarray(self.normal, float)
        u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        h = PLANE_HALF_SIZE_M
        corners = np.array(self.point) + h * np.array([-u - v, u - v, u + v, -u + v])
        return trimesh.Trimesh(corners, [[0, 1, 2], [0, 2, 3]], process=False)


def parse_target(plane: str | None, sphere: str | None) -> Target:
    """The target from `--plane X,Y,Z,NX,NY,NZ` or `--sphere X,Y,Z,R` (metres); one-line ConfigError otherwise."""
    if plane is not None and sphere is not None:
        raise ConfigError("give one target, --plane or --sphere, not both")
    if plane is None and sphere is None:
        raise ConfigError("give the target: --plane X,Y,Z,NX,NY,NZ (a point on it and its normal) or "
                          "--sphere X,Y,Z,R (metres, base frame)")
    text, what, count = (plane, "--plane", 6) if plane is not None else (sphere, "--sphere", 4)
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        shape = "X,Y,Z,NX,NY,NZ" if count == 6 else "X,Y,Z,R"
        raise ConfigError(f"{what} {text!r} must be {count} numbers {shape} (metres, base frame)")
    if plane is not None:
        normal = np.array(values[3:])
        if np.linalg.norm(normal) < 1e-9:
            raise ConfigError(f"--plane {text!r}: the normal (NX, NY, NZ) must not be zero")
        normal /= np.linalg.norm(normal)
        return Target("plane", tuple(values[:3]), tuple(float(v) for v in normal))
    if not 0.0 < values[3] <= 2.0:
        raise ConfigError(f"--sphere {text!r}: the radius {values[3]:g} m must be in (0, 2] (metres)")
    return Target("sphere", tuple(values[:3]), radius=values[3])


@dataclass
class HandEyeFit:
    """The fitted X (4, 4) and how well it and the starting X explain the capture."""

    hand_eye: np.ndarray
    start: np.ndarray
    rms_start_mm: float
    rms_mm: float
    returns: int
    """Zone returns the fit used."""
    views: int
    zero_bin_shift: float = 0.0
    """Bins added to the sensor model's zero bin (0 unless fitted)."""
    iterations: int = 0
    lost: int = 0
    """Zones whose return the fitted X no longer predicts (left out of rms_mm and returns)."""
    std_mm: tuple = (0.0, 0.0, 0.0)
    """One standard deviation of X's translation along the flange's x, y, z (mm)."""
    std_deg: tuple = (0.0, 0.0, 0.0)
    """One standard deviation of X's rotation about the flange's x, y, z (degrees)."""

    @property
    def uncertain(self) -> bool:
        """Whether one standard deviation of X exceeds UNCERTAIN_MM or UNCERTAIN_DEG somewhere."""
        return max(self.std_mm) > UNCERTAIN_MM or max(self.std_deg) > UNCERTAIN_DEG

    @property
    def change_mm(self) -> float:
        return float(np.linalg.norm(self.hand_eye[:3, 3] - self.start[:3, 3]) * 1e3)

    @property
    def change_deg(self) -> float:
        return math.degrees(float(np.linalg.norm(matrix_to_rotvec(self.start[:3, :3].T @ self.hand_eye[:3, :3]))))

    def implausible(self) -> list[str]:
        """How the fitted X left the start or explains the returns beyond what a right fit from a bracket's drawing
        does (see PLAUSIBLE_TILT_DEG), each as a phrase with its unit; empty when nothing does."""
        axis = self.start[:3, 2]
        moved = (self.hand_eye[:3, 3] - self.start[:3, 3]) * 1e3
        along = float(moved @ axis)
        across = float(np.linalg.norm(moved - along * axis))
        tilt = math.degrees(math.acos(float(np.clip(axis @ self.hand_eye[:3, 2], -1.0, 1.0))))
        out = []
        if tilt > PLAUSIBLE_TILT_DEG:
            out.append(f"tilted the sensor's axis {tilt:.0f} deg")
        if across > PLAUSIBLE_ACROSS_MM:
            out.append(f"moved it {across:.0f} mm across its axis")
        if abs(along) > PLAUSIBLE_ALONG_MM:
            out.append(f"moved it {along:+.0f} mm along its axis")
        if self.rms_mm > PLAUSIBLE_RMS_MM:
            out.append(f"left a residual RMS of {self.rms_mm:.1f} mm")
        return out


def peak_bins(hists: np.ndarray, first_bin: int) -> np.ndarray:
    """The bin of each histogram's (..., bins) highest count at or after first_bin."""
    h = np.asarray(hists)
    return first_bin + np.argmax(h[..., first_bin:], axis=-1)


def peak_positions(hists: np.ndarray, peaks: np.ndarray, min_snr: float | None = MIN_SNR) -> np.ndarray:
    """The return's position (bin coordinate) in each histogram (..., bins): the centroid of bin centres (i + 0.5)
    over bins peaks - WINDOW_BINS .. peaks + WINDOW_BINS (peaks (...), see `peak_bins`), above the histogram's median.
    The fit takes the windows from the observed histograms for the predicted ones too, so that the estimator is the
    same on both. NaN where the peak does not stand min_snr Poisson sigmas above the median (None: never)."""
    h = np.asarray(hists, dtype=np.float64)
    flat = h.reshape(-1, h.shape[-1])
    bg = np.median(flat, axis=1)
    k = np.asarray(peaks).reshape(-1)
    offsets = np.arange(-WINDOW_BINS, WINDOW_BINS + 1)
    idx = np.clip(k[:, None] + offsets, 0, flat.shape[1] - 1)
    w = np.maximum(np.take_along_axis(flat, idx, axis=1) - bg[:, None], 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        pos = (w * (idx + 0.5)).sum(axis=1) / w.sum(axis=1)
    if min_snr is not None:
        peak = flat[np.arange(len(flat)), k]
        pos[peak - bg < min_snr * np.sqrt(bg + 1.0)] = np.nan
    return pos.reshape(h.shape[:-1])


class _Predictor:
    """Expected histograms of the target for sensor poses: the simulator's model without photon noise."""

    def __init__(self, model: SensorModel, target: Target):
        self.model = model
        self.sim = Simulator(target.mesh(), model, SimSettings(rays_per_zone=RAYS_PER_ZONE), seed=0)

    def counts(self, sensor_poses: np.ndarray, zero_bin_shift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Expected counts (n, zones, bins) and whether each zone sees the target at all (n, zones)."""
        sim = self.sim
        if zero_bin_shift:
            sim.sensor = self.model.with_(zero_bin=self.model.zero_bin + zero_bin_shift)
        try:
            signal = sim.signal_rates(sensor_poses)
            p = sim.detection_probabilities(signal + max(sim.sensor.background, BACKGROUND_FLOOR))
        finally:
            sim.sensor = self.model
        cycles = self.model.cycles
        return p * cycles, signal.sum(axis=-1) * cycles >= MIN_SIGNAL_COUNTS


def _compose(start: np.ndarray, params: np.ndarray) -> np.ndarray:
    """X = start x [R(rotvec) | t]: params (6,) = rotation vector (rad), translation (m) in the flange frame."""
    out = start.copy()
    out[:3, :3] = start[:3, :3] @ rotvec_to_matrix(params[:3])
    out[:3, 3] = start[:3, 3] + params[3:6]
    return out


def capture_tcp_poses(reader: CaptureReader, data) -> np.ndarray:
    """The actual TCP poses (n, 4, 4) of a capture: metadata `tcp_pose` where recorded, else pose x inv(X)."""
    tcp = []
    inv = invert_rigid(reader.hand_eye)
    for pose, meta in zip(data.poses, data.meta):
        t = meta.get("tcp_pose") if isinstance(meta, dict) else None
        tcp.append(np.asarray(t, dtype=np.float64) if t is not None else pose @ inv)
    tcp = np.asarray(tcp)
    if tcp.shape[1:] != (4, 4) or not np.all(np.isfinite(tcp)):
        raise CaptureError(f"{reader.path}: tcp_pose metadata must hold finite 4x4 poses")
    return tcp


def fit_hand_eye(capture, target: Target, *, fit_zero_bin: bool = False, start: np.ndarray | None = None,
                 iterations: int = 30) -> HandEyeFit:
    """Fit X from a capture folder (see the module docstring). `start`: where the fit begins (default: the X the
    capture was taken with). Raises CaptureError for an unreadable capture, ConfigError when too few zones see the
    target."""
    reader = CaptureReader(Path(capture))
    data = reader.load()
    model = data.sensor
    tcp = capture_tcp_poses(reader, data)
    x0 = np.asarray(reader.hand_eye if start is None else start, dtype=np.float64)
    first_bin = int(math.ceil(model.bin_of_range(MIN_RANGE_M)))
    windows = peak_bins(data.hists, first_bin)
    observed = peak_positions(data.hists, windows)
    predictor = _Predictor(model, target)
    n_params = 7 if fit_zero_bin else 6

    def predict(params: np.ndarray) -> np.ndarray:
        shift = params[6] if fit_zero_bin else 0.0
        counts, seen = predictor.counts(tcp @ _compose(x0, params), shift)
        return np.where(seen, peak_positions(counts, windows, min_snr=None), np.nan)

    params = np.zeros(n_params)
    params[3:6] = _boresight_offset(predictor, tcp, x0, observed, first_bin, model.bin_width_m)
    first = predict(params)
    use = np.isfinite(observed) & np.isfinite(first)
    if use.sum() < 2 * n_params:
        raise ConfigError(f"{reader.path}: only {int(use.sum())} zone returns see the target where it was said to be "
                          f"(need {2 * n_params}); check --plane / --sphere and the capture")

    def residual(p: np.ndarray) -> np.ndarray:
        r = (observed - predict(p))[use]
        # A zone that no longer shows its return costs more than any it could show: a fit that pushes the
        # predictions off the target (a residual of 0 for lost zones) must not look better for it.
        return np.where(np.isfinite(r), r, LOST_ZONE_BINS)

    start_r = (observed - predict(np.zeros(n_params)))[use]
    rms_start = _rms_mm(start_r[np.isfinite(start_r)], model)
    r = residual(params)
    cost, damping, done = float(r @ r), 1e-3, 0
    steps = np.array([1e-4] * 3 + [1e-4] * 3 + [1e-2])[:n_params]
    for done in range(1, iterations + 1):
        jac = _jacobian(residual, params, r, steps)
        jtj, jtr = jac.T @ jac, jac.T @ r
        improved = False
        while damping < 1e8:
            step = -np.linalg.solve(jtj + damping * np.diag(np.diag(jtj) + 1e-12), jtr)
            trial = residual(params + step)
            if float(trial @ trial) < cost:
                params, r, cost, improved = params + step, trial, float(trial @ trial), True
                damping = max(damping / 3.0, 1e-9)
                break
            damping *= 4.0
        if not improved or np.abs(step[:6]).max() < 1e-7:
            break
    seen = np.isfinite(predict(params)[use])
    fit = HandEyeFit(_compose(x0, params), x0, rms_start, _rms_mm(r[seen], model), int(seen.sum()), len(tcp),
                     float(params[6]) if fit_zero_bin else 0.0, done, lost=int((~seen).sum()))
    jac = _flange_rotation(_jacobian(residual, params, r, steps), x0, params)
    _check_determined(jac, reader.path)
    scatter = float(np.sqrt(np.mean(r[seen] ** 2))) if seen.any() else 0.0
    fit.std_mm, fit.std_deg = _uncertainty(jac, max(scatter, SIGMA_FLOOR_BINS))
    return fit


def _jacobian(residual, params: np.ndarray, r: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Forward differences of the residuals (zones,) in each parameter: (zones, parameters)."""
    eye = np.eye(len(params))
    return np.stack([(residual(params + eye[i] * steps[i]) - r) / steps[i] for i in range(len(params))], axis=1)


def _flange_rotation(jac: np.ndarray, start: np.ndarray, params: np.ndarray) -> np.ndarray:
    """The Jacobian (zones, parameters) with its rotation columns taken to a turn of the fitted X about the flange's
    axes, so that the uncertainty is reported in the frame its label names. The fit's rotation vector r turns X on
    the sensor's side of the start (X = R0 R(r)); a step dr of it turns the fitted X by R0 J(r) dr about the
    flange's axes (J: the rotation's left Jacobian, the identity for a small r). On a bracket that turns the sensor
    (90 degrees about z, say) the sensor's axes are not the flange's: reported unrotated, the uncertainty about the
    flange's x was the one about the sensor's y."""
    to_flange = start[:3, :3] @ _left_jacobian(params[:3])
    out = jac.copy()
    out[:, :3] = jac[:, :3] @ np.linalg.inv(to_flange)
    return out


def _left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """J with R(r + dr) = R(J dr) R(r) to first order in dr (3, 3)."""
    theta = float(np.linalg.norm(rotvec))
    k = np.array([[0.0, -rotvec[2], rotvec[1]], [rotvec[2], 0.0, -rotvec[0]], [-rotvec[1], rotvec[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + 0.5 * k
    return (np.eye(3) + (1.0 - math.cos(theta)) / theta ** 2 * k
            + (theta - math.sin(theta)) / theta ** 3 * (k @ k))


def _uncertainty(jac: np.ndarray, sigma_bins: float) -> tuple[tuple, tuple]:
    """One standard deviation of X's translation (flange axes, mm) and rotation (about the flange's axes for a
    Jacobian from `_flange_rotation`, degrees) for returns scattered by sigma_bins: sigma^2 (J^T J)^-1 over every
    fitted parameter (a fitted zero bin takes its share). A direction the views cannot tell apart (J^T J singular)
    comes out infinite."""
    scale = np.linalg.norm(jac, axis=0)
    scale[scale == 0] = 1.0
    _, s, vt = np.linalg.svd(jac / scale, full_matrices=False)
    weight = vt.T ** 2  # (parameter, direction)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        per = np.where(s > s[0] * 1e-9, 1.0 / (s * s), np.inf)
        var = np.where(weight > 1e-12, weight * per, 0.0).sum(axis=1) / scale ** 2 * sigma_bins ** 2
    std = np.sqrt(var)  # residuals in bins, parameters in radians and metres
    return tuple(float(v) for v in std[3:6] * 1e3), tuple(float(v) for v in np.degrees(std[:3]))


def _check_determined(jac: np.ndarray, path) -> None:
    """One-line ConfigError when the views leave part of X undetermined: its uncertainty for returns as steady as a
    sensor's best (SIGMA_FLOOR_BINS) over UNDETERMINED_MM or UNDETERMINED_DEG."""
    std_mm, std_deg = _uncertainty(jac, SIGMA_FLOOR_BINS)
    loose = [f"along {axis} +-{v:.3g} mm" for axis, v in zip("xyz", std_mm) if not v <= UNDETERMINED_MM]
    loose += [f"about {axis} +-{v:.3g} deg" for axis, v in zip("xyz", std_deg) if not v <= UNDETERMINED_DEG]
    if loose:
        raise ConfigError(f"{path}: the views do not determine the hand-eye transform ({', '.join(loose)} in the "
                          f"flange frame): take views that tilt the tool about several axes (rings at several "
                          f"elevations with jitter)")


def _boresight_offset(predictor: _Predictor, tcp: np.ndarray, x0: np.ndarray, observed: np.ndarray, first_bin: int,
                      bin_width_m: float, rounds: int = 5) -> np.ndarray:
    """A translation of X (flange frame, m) along the sensor's boresight that puts the predicted returns at the
    observed ones' median range: a start whose sensor sits centimetres off along its axis (a bracket left out, the
    default identity) puts the predictions outside the observed returns' windows, where the fit below finds no way
    back. Zero when the start is already within half a bin."""
    axis = x0[:3, 2]
    shift = 0.0
    for _ in range(rounds):
        pose = x0.copy()
        pose[:3, 3] = x0[:3, 3] + shift * axis
        counts, seen = predictor.counts(tcp @ pose)
        own = peak_positions(counts, peak_bins(counts, first_bin), min_snr=None)
        off = (observed - own)[seen & np.isfinite(observed) & np.isfinite(own)]
        if off.size == 0 or abs(np.median(off)) < 0.5:
            break
        shift -= float(np.median(off)) * bin_width_m  # a return seen farther than predicted: the sensor sits back
    return shift * axis


def _rms_mm(r: np.ndarray, model: SensorModel) -> float:
    """RMS of residuals in bins as millimetres of one-way range."""
    return float(np.sqrt(np.mean(r * r)) * model.bin_width_m * 1e3) if r.size else math.nan


def hand_eye_toml(x: np.ndarray) -> str:
    """X as the [arm] hand_eye line of a rig config (metres), to 1e-9: the arm's pose conversion wants rotations
    orthonormal to 1e-6 (the config's reader also projects what it is given onto the nearest rotation)."""
    rows = ",\n            ".join("[" + ", ".join(f"{v:.9f}" for v in row) + "]" for row in x)
    return f"hand_eye = [{rows}]"
