"""Hand-eye calibration: the flange-to-sensor transform X ([arm] hand_eye) fitted from a capture of a known target.

Every measurement of a daemon capture records the arm's actual TCP pose T (metadata `tcp_pose`; otherwise the
stored sensor pose times the inverse of the stored X). With the right X the sensor sat at T x X, and a known target
(a plane: the table; or a sphere) seen from there gives histograms whose first return lies where the sensor model
puts it. The fit moves X until, for every view and zone, the *observed* return's position (a windowed centroid
around the histogram's peak, in bins) matches the *predicted* one: the same estimator applied to the histogram the
simulator expects for that zone (`protocol.simulator`: the zone's rays, the pulse, gains, crosstalk, pile-up), so
the estimator's own biases cancel; a zone whose predicted return peaks outside the observed return's window is lost,
not a match. Levenberg-Marquardt over six parameters (a rotation vector applied on the sensor's side of X's rotation,
a translation in the flange frame), optionally a seventh: a shift of the sensor model's zero bin; before it, the start
is moved along the sensor's axis to the returns' median range (a start centimetres off along it leaves the fit no way
back), and it is tried turned four ways about that axis (TURNS_DEG). After it, X's uncertainty (sigma^2 (J^T J)^-1,
over one residual and one Jacobian row per pose and zone, each the mean over the pose's frames: frames of one pose
share its error, so more frames do not make X more certain); views that leave part of X undetermined are refused
rather than fitted. Both uncertainties are given along and about the flange's axes. A one-zone sensor sees the same
at every turn about its boresight: that turn is held at the start's (not fitted, not tried four ways) and reported
as not determined; its rotation's uncertainty is the tilt of its axis about the sensor's own x and y.

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
"""A fit is refused when, for returns scattered by SIGMA_FLOOR_BINS (one per pose and zone, however many frames),
one standard deviation of X's translation along a flange axis or of its rotation about one exceeds these: the views
leave that part of X to the optimiser's drift (views all turned about one axis, rings without jitter, too few views:
tens of millimetres to metres); views tilted 5-30 degrees every way give about 1 mm and 0.6 degrees."""
RIGID_TOL = 1e-4
"""A recorded tcp_pose's rotation must be orthonormal to this (the simulator's tolerance for the poses it renders)."""
TURNS_DEG = (0.0, 90.0, 180.0, 270.0)
SCOUT_ITERATIONS = 2
"""The fit starts from the given X turned each of TURNS_DEG about the sensor's boresight (a connector's orientation
may be unknown, and a local fit from 135-180 degrees off settles in a wrong minimum), takes SCOUT_ITERATIONS steps
from each and carries on from the one with the least cost: after two, the start nearest the right turn (within 45
degrees) led for every turn tried round the circle, and the four scouts cost about two fits from one start."""
UNCERTAIN_MM = 5.0
UNCERTAIN_DEG = 2.0
"""Above these (one standard deviation, for the fit's own scatter) `calibrate` warns: the recipe in the docs gives
about 2.5 mm and 0.7 degrees for returns scattered by SIGMA_FLOOR_BINS."""

PLAUSIBLE_TILT_DEG = 10.0
PLAUSIBLE_ACROSS_MM = 20.0
PLAUSIBLE_ALONG_MM = 20.0
PLAUSIBLE_ALONG_UNMOUNTED_MM = 100.0
PLAUSIBLE_RMS_MM = 10.0
PLAUSIBLE_LOST = 0.2
"""Beyond these `calibrate` warns that the fit is more likely wrong than the bracket: a bracket's drawing or a
caliper measurement puts the sensor's axis within a few degrees and its aperture within a few millimetres, and a
start whose axis is tilted more than about 20 degrees can settle in a wrong minimum (firmware_notes/hand_eye.md), so a
fitted tilt of the axis over 10 degrees or a shift over 20 mm across or along the axis is twice a careless start.
Along the axis a start without a translation (the default identity, a bracket left out: the fit moves it back first)
may be off by as much as a bracket is long (10 cm). A height error in the target (a plane's point measured with the
pointer's TCP not active, off by the pointer's length) or a zero bin off goes into X's offset along the axis and
leaves small residuals (80 mm: 2 mm RMS, a z uncertainty of 0.3 mm): only this limit sees it. A turn about the axis
is not limited (the connector's orientation may be unknown; the fit tries four turns). A residual RMS over 10 mm is
more than real data leaves with the right target (a few millimetres), and on a plane more than a fifth of the zone
returns left off it means something else in view (an object standing on it, a wrong plane)."""
HEIGHT_ACROSS = 0.3
"""A plane given too high or too low moves the fitted X along the sensor's axis and across it by up to about a
quarter of that (tilted views: 120 mm along came with 22 mm across); a fit that moved no more across than this share
is put down to the target's height first."""
UNMOUNTED_MM = 1.0
"""A start whose translation is shorter than this is taken for one without the bracket (the default identity)."""


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
    """Zone returns the fit used: one per frame and zone (each frame of a view is fitted on its own)."""
    views: int
    """Poses the capture was taken at (distinct pose indices)."""
    zero_bin_shift: float = 0.0
    """Bins added to the sensor model's zero bin (0 unless fitted)."""
    iterations: int = 0
    lost: int = 0
    """Zones that show a return which the fitted X does not put on the target within its window (left out of
    rms_mm and returns)."""
    lost_start: int = 0
    """Of the `returns` zones, those whose return the start puts off the target or outside its window (left out of
    rms_start_mm, which covers the other returns - lost_start zones only)."""
    std_mm: tuple = (0.0, 0.0, 0.0)
    """One standard deviation of X's translation along the flange's x, y, z (mm)."""
    std_deg: tuple = (0.0, 0.0, 0.0)
    """One standard deviation of X's rotation about the flange's x, y, z (degrees); where turn_determined is False,
    two: of the tilt of the sensor's axis about the sensor's own x and y."""
    bin_width_mm: float = 0.0
    """The capture's histogram bin, one-way range (mm): a return more than WINDOW_BINS of them off is lost."""
    kind: str = "plane"
    """The target's kind ('plane' or 'sphere'): beside a sphere, zones that see something else are expected."""
    turn_deg: float = 0.0
    """Which of TURNS_DEG about the sensor's boresight the fit went on from (0: the start as given)."""
    frames: int = 0
    """Measurements fitted: frames_per_pose of them at each view (0: one a view)."""
    turn_determined: bool = True
    """False for a sensor whose histograms do not tell a turn about its boresight (one zone: `turn_observable`):
    X keeps the start's turn there, which the fit says nothing of (std_deg leaves it out)."""

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
        tilt, across, along = self._moved()
        out = []
        if tilt > PLAUSIBLE_TILT_DEG:
            out.append(f"tilted the sensor's axis {tilt:.0f} deg")
        if across > PLAUSIBLE_ACROSS_MM:
            out.append(f"moved it {across:.0f} mm across its axis")
        if abs(along) > self.along_limit_mm:
            out.append(f"moved it {along:+.0f} mm along its axis")
        if self.rms_mm > PLAUSIBLE_RMS_MM:
            out.append(f"left a residual RMS of {self.rms_mm:.1f} mm")
        if self._off_plane:
            out.append(f"left {self.lost} of the {self.returns + self.lost} zone returns off the plane")
        return out

    @property
    def _off_plane(self) -> bool:
        """Whether more than PLAUSIBLE_LOST of the zone returns lie off a plane target (something else in view)."""
        shown = self.returns + self.lost
        return self.kind == "plane" and shown > 0 and self.lost > PLAUSIBLE_LOST * shown

    @property
    def along_limit_mm(self) -> float:
        """How far along the sensor's axis the fit may move X without a warning (see PLAUSIBLE_ALONG_MM)."""
        unmounted = np.linalg.norm(self.start[:3, 3]) * 1e3 < UNMOUNTED_MM
        return PLAUSIBLE_ALONG_UNMOUNTED_MM if unmounted else PLAUSIBLE_ALONG_MM

    def likely_causes(self) -> str:
        """The likely causes of an implausible fit, likeliest first. A fit that moved X mostly along the sensor's axis
        and explains the returns points at the target's height (or the zero bin): a height error leaves no other
        trace. Many returns left off a plane point at something else in view."""
        tilt, across, along = self._moved()
        if self._off_plane:
            return ("likely something standing on the plane, or a wrong target (its height, a sign or axis of "
                    "--plane), or a start whose axis is tilted more than about 20 deg")
        height = (abs(along) > self.along_limit_mm and tilt <= PLAUSIBLE_TILT_DEG and self.rms_mm <= PLAUSIBLE_RMS_MM
                  and across <= max(PLAUSIBLE_ACROSS_MM, HEIGHT_ACROSS * abs(along)))
        if height:
            return ("likely the target's height: a point of --plane / --sphere measured with the wrong TCP active "
                    "(off by the pointer's length) or a wrong Z, or the sensor model's zero bin (calibration.md); a "
                    "height error goes into X along the sensor's axis and leaves small residuals; else a wrong "
                    "target (a sign or axis of --plane / --sphere) or something standing on the plane")
        return ("likely a wrong target (a sign or axis of --plane / --sphere, a point measured with the wrong TCP), "
                "something standing on the plane, or a start whose axis is tilted more than about 20 deg")

    def _moved(self) -> tuple[float, float, float]:
        """How the fit moved X from the start: the tilt of the sensor's axis (degrees), the aperture's shift across
        the axis and along it (mm)."""
        axis = self.start[:3, 2]
        moved = (self.hand_eye[:3, 3] - self.start[:3, 3]) * 1e3
        along = float(moved @ axis)
        across = float(np.linalg.norm(moved - along * axis))
        tilt = math.degrees(math.acos(float(np.clip(axis @ self.hand_eye[:3, 2], -1.0, 1.0))))
        return tilt, across, along


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
    """The actual TCP poses (n, 4, 4) of a capture: metadata `tcp_pose` where recorded, else pose x inv(X). One-line
    CaptureError naming the measurement when a recorded tcp_pose is not a rigid 4x4 transform (hand-edited or damaged
    metadata)."""
    tcp = []
    inv = invert_rigid(reader.hand_eye)
    for i, (pose, meta) in enumerate(zip(data.poses, data.meta)):
        t = meta.get("tcp_pose") if isinstance(meta, dict) else None
        tcp.append(pose @ inv if t is None else _tcp_pose(t, f"{reader.path}: measurement {i}: tcp_pose"))
    return np.asarray(tcp, dtype=np.float64).reshape(-1, 4, 4)


def _tcp_pose(value, where: str) -> np.ndarray:
    """One recorded tcp_pose as a rigid (4, 4) transform, orthonormal to the simulator's tolerance; CaptureError
    naming `where` otherwise."""
    try:
        t = np.asarray(value, dtype=np.float64)
    except (ValueError, TypeError):
        raise CaptureError(f"{where} must be a 4x4 list of numbers (metres), got {str(value)[:60]!r}") from None
    if t.shape != (4, 4):
        raise CaptureError(f"{where} must be a 4x4 list of numbers (metres), got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise CaptureError(f"{where} holds non-finite values")
    if np.abs(t[3] - [0.0, 0.0, 0.0, 1.0]).max() > RIGID_TOL:
        raise CaptureError(f"{where} is not a rigid transform (last row {t[3].tolist()}, not [0, 0, 0, 1])")
    err = float(np.abs(t[:3, :3].T @ t[:3, :3] - np.eye(3)).max())
    if err > RIGID_TOL or np.linalg.det(t[:3, :3]) < 0:
        raise CaptureError(f"{where} is not a rigid transform (rotation off orthonormal by {err:.2g} or mirrored)")
    return t


def _turned(x: np.ndarray, deg: float) -> np.ndarray:
    """X turned `deg` degrees about the sensor's boresight (its own z): the aperture and the axis stay put."""
    out = x.copy()
    out[:3, :3] = x[:3, :3] @ rotvec_to_matrix([0.0, 0.0, math.radians(deg)])
    return out


def _on_target(counts: np.ndarray, seen: np.ndarray, windows: np.ndarray, first_bin: int) -> np.ndarray:
    """The predicted return's position in each observed window (bins), NaN where the zone does not see the target
    or its predicted return peaks outside the observed window: there the window holds only the predicted
    background or a pulse's tail, whose centroid lies near the window's centre and would score a miss as a match."""
    pos = peak_positions(counts, windows, min_snr=None)
    inside = np.abs(peak_bins(counts, first_bin) - windows) <= WINDOW_BINS
    return np.where(seen & inside, pos, np.nan)


def _levenberg_marquardt(residual, params: np.ndarray, steps: np.ndarray, iterations: int):
    """Up to `iterations` damped Gauss-Newton steps from params; (params, residuals, iterations, converged)."""
    r = residual(params)
    cost, damping, done, converged = float(r @ r), 1e-3, 0, False
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
            converged = True
            break
    return params, r, done, converged


def _fit_best_turn(residual_from, starts: list, steps: np.ndarray, iterations: int):
    """A few steps from each start (turn, X, params), then on from the one whose returns are explained best: a local
    fit does not come back from every turn about the axis (from 180 degrees it settled 64 mm and 173 degrees off at
    8 mm RMS). (turn, X, params, residuals, iterations)."""
    scouted = []
    for turn, x, params in starts:
        params, r, done, converged = _levenberg_marquardt(residual_from(x), params, steps,
                                                          min(SCOUT_ITERATIONS, iterations))
        scouted.append((float(r @ r), turn, x, params, r, done, converged))
    _, turn, x, params, r, done, converged = min(scouted, key=lambda c: c[0])
    if not converged and iterations > done:
        params, r, more, _ = _levenberg_marquardt(residual_from(x), params, steps, iterations - done)
        done += more
    return turn, x, params, r, done


def fit_hand_eye(capture, target: Target, *, fit_zero_bin: bool = False, start: np.ndarray | None = None,
                 iterations: int = 30) -> HandEyeFit:
    """Fit X from a capture folder (see the module docstring). `start`: where the fit begins (default: the X the
    capture was taken with); the fit also tries it turned about the sensor's boresight (TURNS_DEG) and keeps the
    turn that explains the returns best after SCOUT_ITERATIONS. A one-zone sensor's turn about its boresight is
    held at the start's (see `turn_observable`). Raises CaptureError for an unreadable capture, ConfigError when
    too few zones see the target."""
    reader = CaptureReader(Path(capture))
    data = reader.load()
    model = data.sensor
    tcp = capture_tcp_poses(reader, data)
    x0 = np.asarray(reader.hand_eye if start is None else start, dtype=np.float64)
    first_bin = int(math.ceil(model.bin_of_range(MIN_RANGE_M)))
    windows = peak_bins(data.hists, first_bin)
    observed = peak_positions(data.hists, windows)
    shown = np.isfinite(observed)
    # The (pose, zone) each return belongs to: the frames of one pose share its error, so the independent samples
    # are these, not the frames.
    n_zones = observed.shape[-1]
    groups = (data.pose_indices[:, None] * n_zones + np.arange(n_zones))[shown]
    predictor = _Predictor(model, target)
    turn_known = turn_observable(model)
    n_params = 7 if fit_zero_bin else 6
    free = np.array([i for i in range(n_params) if turn_known or i != 2])  # 2: the turn about the boresight
    steps = np.array([1e-4] * 3 + [1e-4] * 3 + [1e-2])[free]

    def full(p: np.ndarray) -> np.ndarray:
        out = np.zeros(n_params)
        out[free] = p
        return out

    def predict(x: np.ndarray, params: np.ndarray) -> np.ndarray:
        counts, seen = predictor.counts(tcp @ _compose(x, params), params[6] if fit_zero_bin else 0.0)
        return _on_target(counts, seen, windows, first_bin)

    def residual_from(x: np.ndarray):
        def residual(p: np.ndarray) -> np.ndarray:
            # Every zone that shows a return counts, the same set from every start so that their costs compare. A
            # zone whose predicted return is off the target or its window costs more than any it could show: a fit
            # that pushes the predictions away (a residual of 0 for lost zones) must not look better for it.
            r = observed[shown] - predict(x, full(p))[shown]
            return np.where(np.isfinite(r), r, LOST_ZONE_BINS)
        return residual

    starts = []
    for turn in TURNS_DEG if turn_known else (0.0,):
        x = _turned(x0, turn)
        params = np.zeros(n_params)
        params[3:6] = _boresight_offset(predictor, tcp, x, observed, first_bin, model.bin_width_m)
        on = np.isfinite(predict(x, params)[shown])
        starts.append((turn, x, params[free], len(np.unique(groups[on]))))
    matched = max(m for *_, m in starts)
    if matched < 2 * len(free):
        raise ConfigError(f"{reader.path}: only {matched} zone returns see the target where it was said to be "
                          f"(need {2 * len(free)}, counting a zone once per view); check --plane / --sphere and the "
                          f"capture")
    turn, x, params, r, done = _fit_best_turn(residual_from, [s[:3] for s in starts], steps, iterations)
    fitted_params = full(params)
    fitted = np.isfinite(predict(x, fitted_params)[shown])
    r_start = observed[shown] - predict(x0, np.zeros(n_params))[shown]
    both = fitted & np.isfinite(r_start)
    fit = HandEyeFit(_compose(x, fitted_params), x0, _rms_mm(r_start[both], model), _rms_mm(r[fitted], model),
                     int(fitted.sum()), len(np.unique(data.pose_indices)),
                     float(fitted_params[6]) if fit_zero_bin else 0.0, done, lost=int((~fitted).sum()),
                     lost_start=int((fitted & ~both).sum()), bin_width_mm=model.bin_width_m * 1e3, kind=target.kind,
                     turn_deg=turn, frames=len(tcp), turn_determined=turn_known)
    # One row and one residual per (pose, zone), each the mean over the pose's frames: k frames of a pose are not k
    # independent looks at X (they share the arm's repeatability and the target's placement), and counted as such
    # they shrank the uncertainty, and the check that refuses undetermined views, by sqrt(k). A zone whose return
    # leaves its window within a difference step has no derivative there: its row (the jump to LOST_ZONE_BINS over
    # 1e-4) claimed a turn known to 0.2 deg that was known to 1.4.
    def raw(p: np.ndarray) -> np.ndarray:
        return observed[shown] - predict(x, full(p))[shown]  # NaN where the return is lost

    jac = _jacobian(raw, params, np.where(fitted, r, np.nan), steps)
    steady = fitted & np.isfinite(jac).all(axis=1)
    jac = _per_pose(jac[steady], groups[steady])
    per_pose = _per_pose(r[steady], groups[steady])
    n_rot = 3 if turn_known else 2
    if turn_known:
        jac = _flange_rotation(jac, x, fitted_params)
    _check_determined(jac, reader.path, n_rot)
    scatter = float(np.sqrt(np.mean(per_pose ** 2)))
    fit.std_mm, fit.std_deg = _uncertainty(jac, max(scatter, SIGMA_FLOOR_BINS), n_rot)
    return fit


def turn_observable(model: SensorModel) -> bool:
    """Whether the sensor's histograms tell a turn about its boresight: not with one zone (a cone about the
    boresight sees the same at every turn; a lone zone of another shape hardly less), so the fit holds that turn
    at the start's and reports it as not determined."""
    return len(model.zones) > 1


def _per_pose(values: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """The mean of `values` (rows) over the rows of each group, groups in sorted order; one row of zeros when
    there are none (nothing is determined then)."""
    if len(values) == 0:
        return np.zeros((1,) + values.shape[1:])
    _, inverse = np.unique(groups, return_inverse=True)
    sums = np.zeros((inverse.max() + 1,) + values.shape[1:])
    np.add.at(sums, inverse, values)
    counts = np.bincount(inverse).astype(np.float64)
    return sums / counts.reshape((-1,) + (1,) * (values.ndim - 1))


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
    if theta < 1e-4:
        # Its series: below this the closed form's 1 - cos(theta) loses its digits (nothing at all below 1e-8).
        return np.eye(3) + 0.5 * k + (k @ k) / 6.0
    return (np.eye(3) + (1.0 - math.cos(theta)) / theta ** 2 * k
            + (theta - math.sin(theta)) / theta ** 3 * (k @ k))


def _uncertainty(jac: np.ndarray, sigma_bins: float, n_rot: int = 3) -> tuple[tuple, tuple]:
    """One standard deviation of X's translation (flange axes, mm) and rotation (about the flange's axes for a
    Jacobian from `_flange_rotation`, degrees) for returns scattered by sigma_bins: sigma^2 (J^T J)^-1 over every
    fitted parameter (a fitted zero bin takes its share). A direction the views cannot tell apart (J^T J singular)
    comes out infinite. The Jacobian's columns: n_rot rotations (3; 2 where the turn about the boresight is held:
    the tilts about the sensor's own x and y), the translation along x, y, z, a zero bin if fitted."""
    scale = np.linalg.norm(jac, axis=0)
    scale[scale == 0] = 1.0
    _, s, vt = np.linalg.svd(jac / scale, full_matrices=False)
    weight = vt.T ** 2  # (parameter, direction)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        per = np.where(s > s[0] * 1e-9, 1.0 / (s * s), np.inf)
        var = np.where(weight > 1e-12, weight * per, 0.0).sum(axis=1) / scale ** 2 * sigma_bins ** 2
    std = np.sqrt(var)  # residuals in bins, parameters in radians and metres
    return (tuple(float(v) for v in std[n_rot:n_rot + 3] * 1e3),
            tuple(float(v) for v in np.degrees(std[:n_rot])))


def _check_determined(jac: np.ndarray, path, n_rot: int = 3) -> None:
    """One-line ConfigError when the views leave part of X undetermined: its uncertainty for returns as steady as a
    sensor's best (SIGMA_FLOOR_BINS) over UNDETERMINED_MM or UNDETERMINED_DEG. n_rot: as for `_uncertainty` (2: the
    tilts about the sensor's own x and y, the turn about its boresight being held)."""
    std_mm, std_deg = _uncertainty(jac, SIGMA_FLOOR_BINS, n_rot)
    about = "about " if n_rot == 3 else "about the sensor's own "
    loose = [f"along {axis} {_spread(v, 'mm', math.inf)}" for axis, v in zip("xyz", std_mm)
             if not v <= UNDETERMINED_MM]
    loose += [f"{about}{axis} {_spread(v, 'deg', 180.0)}" for axis, v in zip("xyz", std_deg)
              if not v <= UNDETERMINED_DEG]
    if loose:
        raise ConfigError(f"{path}: the views do not determine the hand-eye transform ({', '.join(loose)} in the "
                          f"flange frame): take views that tilt the tool about several axes (rings at several "
                          f"elevations with jitter)")


def _spread(value: float, unit: str, whole: float) -> str:
    """One loose part of X's uncertainty in words: "+-12.3 mm", or "wholly undetermined" where the views say
    nothing of it (an infinite spread, or a turn of more than half a revolution: `whole`), which "+-inf mm" or
    "+-1.4e+04 deg" would only say in a way that reads like a fault of the program."""
    return f"+-{value:.3g} {unit}" if math.isfinite(value) and value <= whole else "wholly undetermined"


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
