"""Hand-eye calibration: the flange-to-sensor transform X ([arm] hand_eye) fitted from a capture of a known target.

Every measurement of a daemon capture records the arm's actual TCP pose T (metadata `tcp_pose`; otherwise the
stored sensor pose times the inverse of the stored X). With the right X the sensor sat at T x X, and a known target
(a plane: the table; or a sphere) seen from there gives histograms whose first return lies where the sensor model
puts it. The fit moves X until, for every view and zone, the *observed* return's position (a windowed centroid
around the histogram's peak, in bins) matches the *predicted* one: the same estimator applied to the histogram the
simulator expects for that zone (`protocol.simulator`: the zone's rays, the pulse, gains, crosstalk, pile-up), so
the estimator's own biases cancel. Levenberg-Marquardt over six parameters (a rotation vector and a translation,
applied to X on the flange side), optionally a seventh: a shift of the sensor model's zero bin.

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
RAYS_PER_ZONE = 64
"""Rays per zone of the predicted histograms (a fixed, deterministic set: the fit sees a smooth function)."""
PLANE_HALF_SIZE_M = 3.0
"""Half the side of the square that stands for an infinite plane."""


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

    @property
    def change_mm(self) -> float:
        return float(np.linalg.norm(self.hand_eye[:3, 3] - self.start[:3, 3]) * 1e3)

    @property
    def change_deg(self) -> float:
        return math.degrees(float(np.linalg.norm(matrix_to_rotvec(self.start[:3, :3].T @ self.hand_eye[:3, :3]))))


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
    first = predict(params)
    use = np.isfinite(observed) & np.isfinite(first)
    if use.sum() < 2 * n_params:
        raise ConfigError(f"{reader.path}: only {int(use.sum())} zone returns see the target where it was said to be "
                          f"(need {2 * n_params}); check --plane / --sphere and the capture")

    def residual(p: np.ndarray) -> np.ndarray:
        r = (observed - predict(p))[use]
        return np.where(np.isfinite(r), r, 0.0)  # a zone that no longer sees the target pulls no further

    r = residual(params)
    rms_start = _rms_mm(r, model)
    cost, damping, done = float(r @ r), 1e-3, 0
    steps = np.array([1e-4] * 3 + [1e-4] * 3 + [1e-2])[:n_params]
    for done in range(1, iterations + 1):
        jac = np.stack([(residual(params + np.eye(n_params)[i] * steps[i]) - r) / steps[i]
                        for i in range(n_params)], axis=1)
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
    return HandEyeFit(_compose(x0, params), x0, rms_start, _rms_mm(r, model), int(use.sum()), len(tcp),
                      float(params[6]) if fit_zero_bin else 0.0, done)


def _rms_mm(r: np.ndarray, model: SensorModel) -> float:
    """RMS of residuals in bins as millimetres of one-way range."""
    return float(np.sqrt(np.mean(r * r)) * model.bin_width_m * 1e3) if r.size else math.nan


def hand_eye_toml(x: np.ndarray) -> str:
    """X as the [arm] hand_eye line of a rig config (metres), to 1e-9: the arm's pose conversion wants rotations
    orthonormal to 1e-6 (the config's reader also projects what it is given onto the nearest rotation)."""
    rows = ",\n            ".join("[" + ", ".join(f"{v:.9f}" for v in row) + "]" for row in x)
    return f"hand_eye = [{rows}]"
