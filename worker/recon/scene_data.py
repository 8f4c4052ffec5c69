"""A capture loaded into tensors for reconstruction: counts per view, poses, pulse, background, scene bounds, table.

Frames recorded at one pose (same `pose_index`) are summed into one histogram per zone (their cycles add up), since
the sensor did not move between them. Bins listed in the sensor model's `ignore_bins`, and bins where any frame hit
the counter's ceiling (`max_count`; their counts zeroed, `load_scene`), are masked out of every loss, as is every bin
of a histogram no sensor could have produced in any of its frames (`protocol.plausibility`: all zero, saturated, more
counts than a first-photon sensor's cycles allow, ...).

The manifest's `scene` dict may say (all optional, metres):
- `"center": [x, y, z]`, `"radius": r` — a sphere that holds the object (else found from the views' first returns,
  see `_scene_sphere`);
- `"table": {"normal": [nx, ny, nz], "offset": d}` (the plane n . x = d, n pointing up) or `"table": {"z": h}`, or
  `"table": true` for a horizontal table whose height is fitted, or `"table": false`; measured scenes that say
  nothing get a fitted table (on the arm rig the object stands on one), simulated ones none;
- `"floor_z": z` — nothing is solid below this height (a finite number within MAX_FLOOR_M, checked here);
- `"real": true|false` — measured data (default: false for a simulated rig (`rig.kind` "simulated") or a daemon's
  simulated sensor (`rig.sensor.backend` "sim"), else whether the sensor model carries reference histograms, i.e.
  is hardware). Only measured data take their pulse from reference histograms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.plausibility import implausible, survey_counts
from spadscan.protocol.sensor_model import SensorModel

from ..capture_kind import is_measured
from ..carving.bounds import RADIUS_FRACTION_MAX, given_sphere
from ..pulse import pulse_kernel
from ..table_height import TablePlane, named_table

RADIUS_FRACTION = 0.6  # scene radius / nearest sensor's distance, when no return locates the object
MAX_FLOOR_M = 100.0
"""A scene's floor_z (metres) beyond this is no floor of a lab's scene: a unit or a typing error."""
BEYOND_BOUND_SHARE = 0.01
"""A scene sphere that leaves more than this share of the first returns outside is said to cut the object."""
TABLE_RETURN_BAND_M = 0.03
"""A first return this near the table top (m) is taken for the table's: a view's return along its boresight is
placed to within a bin or two (the tmf8820's: 1.4 cm of range each), and a low view meets the top far out."""
FAR_RETURN_MARGIN = 1.25
"""The scene sphere reaches at least this many times the farthest view's return from its centre. Most views of a
thin object return from near the point they aim at (a 32 cm coat rack's 12 mm pole: the 90th percentile 3.6 cm from
the centre), and only the few views above see its top (the farthest return 29 cm away): 3 x the percentile cut the
rack off at 11 cm, and the fit had nothing to fit (57.8 mm). 1.25 changes the sphere of no other capture of the
benchmarks (each one's percentile rule or the sensors' distance gives more)."""


@dataclass
class SceneData:
    """One capture, ready for the renderer. V views, Z zones, B bins."""

    capture: Path
    """The capture folder."""
    sensor: SensorModel
    """The capture's sensor model."""
    counts: torch.Tensor
    """(V, Z, B) photon counts per view (frames of one pose summed)."""
    cycles: torch.Tensor
    """(V,) laser cycles behind each view's histograms."""
    valid: torch.Tensor
    """(V, Z, B) bool: bins that enter the loss (not ignored, not saturated)."""
    poses: torch.Tensor
    """(V, 4, 4) sensor-to-world transforms, metres."""
    pose_index: np.ndarray
    """(V,) the capture's pose index of each view."""
    reference: np.ndarray | None
    """(B,) mean reference histogram of a measured capture (gives the pulse), or None."""
    pulse_source: str
    """'reference' (from the capture's reference histograms) or 'sensor model'."""
    background: torch.Tensor
    """(V, Z) flat background, photons per bin per cycle (> 0)."""
    background_source: str
    """'estimated' (from bins before any possible return) or 'sensor model'."""
    center: torch.Tensor
    """(3,) centre of the scene sphere, metres."""
    radius: float
    """Radius of the scene sphere that holds the object, metres."""
    table: TablePlane | None
    """The table plane, or None (no table in this scene)."""
    real: bool
    """Measured data (enables the TV term)."""
    scene: dict
    """The manifest's scene dict as read."""
    state: str = "complete"
    """The capture's state: 'complete', or 'running' / 'aborted' for a scan not (yet) finished."""
    usable: torch.Tensor | None = None
    """(V, Z) bool: histograms the capture holds data in (False: one no sensor could have produced, in some frame;
    all its bins are invalid too); None: all of them."""
    bound_note: str | None = None
    """Why part of the object may lie outside the scene sphere (views too near its centre keep it small), or None."""
    pulse_note: str | None = None
    """Why a measured capture's pulse is the sensor model's though it holds reference histograms (they show no
    clear peak: all zero, saturated, flat), or None."""

    def pulse(self, oversample: int = 1) -> tuple[np.ndarray, int]:
        """(kernel (K,) summing to 1, origin): kernel[origin + k] is the response k / oversample bins after the
        arrival (see `pulse.pulse_kernel`)."""
        kernel, origin, _ = pulse_kernel(self.sensor, self.reference, oversample)
        return kernel, origin

    @property
    def n_views(self) -> int:
        return int(self.counts.shape[0])

    @property
    def box(self) -> torch.Tensor:
        """(2, 3) axis-aligned box around the scene sphere, cut at the table if there is one (min row, max row)."""
        lo, hi = self.center - self.radius, self.center + self.radius
        if self.table is not None and abs(self.table.normal[2]) > 0.99 and not self.table.fitted:
            lo = lo.clone()
            lo[2] = max(float(lo[2]), self.table.offset / self.table.normal[2] - 0.01 * self.radius)
        return torch.stack([lo, hi])


def load_scene(capture, device="cpu", dtype=torch.float32) -> SceneData:
    """Read a capture folder into a SceneData on `device` in `dtype` (counts and poses; bools stay bool)."""
    capture = Path(capture)
    data = CaptureReader(capture).load()
    sensor = data.sensor
    if data.hists.shape[0] == 0:
        raise CaptureError(f"{capture}: holds no measurements")
    views = data.by_pose()
    counts, frames = views.counts, views.frames
    saturated = views.in_any_frame(data.hists >= sensor.max_count)
    # A histogram no sensor could have produced in any of a pose's frames (all zero: a dropped frame) says nothing
    # of its zone: left out of the fit and of carving, where it would prove the zone's whole field of view empty.
    # One with more counts than a first-photon sensor's cycles allow (a corrupt bin) would pull the fitted albedo
    # and spoil the fit of every other histogram.
    broken = views.in_any_frame(_implausible(data, capture))
    # Left out means left out of everything: the scene's bound, the table's search and the background read counts
    # too, and a corrupt bin of a left-out histogram would otherwise put the table under a spurious peak. So is a bin
    # at the counter's limit, which holds no count (every preset's counter holds more than a frame's cycles: the value
    # is a corrupt one): masked out of the bins' terms only, it stayed in the fit's "no photon" term (a 2**32-1 there
    # read as every cycle having seen a photon: a sphere 115 mm off after 50 steps, 56 without it), the first returns
    # (each view's return put in that bin), the scene's bound, the table and the background.
    valid = ~saturated & ~broken[..., None]
    counts = np.where(valid, counts, 0.0)
    poses = data.poses[views.first]
    if sensor.ignore_bins:
        valid[..., list(sensor.ignore_bins)] = False
    cycles = frames * float(sensor.cycles)

    scene = dict(data.manifest.get("scene") or {})
    _check_floor(scene, capture)
    real = is_measured(scene, data.manifest, sensor)
    points = first_returns(counts, poses, sensor)
    center, radius, bound_note = _scene_sphere(scene, poses, points, sensor, capture, real)
    table = _table(scene, center, radius, real, points, capture)
    reference = data.reference.mean(axis=0) if (real and data.reference is not None) else None
    kernel, origin, pulse_source = pulse_kernel(sensor, reference)
    pulse_note = None
    if reference is not None and pulse_source != "reference":
        pulse_note = (f"the capture's reference histograms show no clear pulse (no peak 5 standard deviations over "
                      f"their floor: the sensor's reference path dark, saturated or flat), so the fit takes the "
                      f"{sensor.name} sensor model's pulse, which may not be this unit's; check the sensor")
    reference = reference if pulse_source == "reference" else None
    background, bg_source = _background(counts, cycles, poses, center, radius, sensor, origin, real)

    t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype, device=device)  # noqa: E731
    return SceneData(
        capture=capture, sensor=sensor, counts=t(counts), cycles=t(cycles),
        valid=torch.as_tensor(valid, device=device), poses=t(poses), pose_index=data.pose_indices[views.first],
        reference=reference, pulse_source=pulse_source,
        background=t(background), background_source=bg_source,
        center=t(center), radius=float(radius), table=table, real=real, scene=scene, bound_note=bound_note,
        usable=torch.as_tensor(~broken, device=device), pulse_note=pulse_note,
        state=str(data.manifest["state"]),
    )


def bound_warning(nearest_m: float, radius_m: float, beyond: float) -> str:
    """The line saying that views `nearest_m` from the scene's centre keep its bound to `radius_m` and a share
    `beyond` of the first returns lie outside it: that part of the object is not reconstructed."""
    return (f"views as near as {nearest_m * 1e3:.0f} mm to the scene's centre keep its bound to {radius_m * 1e3:.0f} "
            f"mm, and {beyond:.0%} of the first returns lie beyond it: that part of the object cannot be "
            f"reconstructed (scan from farther, or give scene.center and scene.radius in the capture's scan.json)")


def _check_floor(scene: dict, capture: Path) -> None:
    """One-line CaptureError for a scene `floor_z` that is no finite number of metres (NaN trained on and failed as a
    diverged fit; true read as a 1 m floor)."""
    if "floor_z" not in scene or scene["floor_z"] is None:
        return
    z = scene["floor_z"]
    if isinstance(z, bool) or not isinstance(z, (int, float)) or not math.isfinite(z) or abs(z) > MAX_FLOOR_M:
        raise CaptureError(f"{capture / 'scan.json'}: scene floor_z {z!r} is not a height in metres (a finite "
                           f"number within +-{MAX_FLOOR_M:g} m)")


def _implausible(data, capture: Path) -> np.ndarray:
    """The mask (N, Z) of the histograms of `data` (a CaptureData) no sensor could have produced
    (protocol.plausibility, the first-photon cycles bound included, as the capture's reader sets it); a CaptureError,
    in one line, when that is all of them: nothing would be left to fit."""
    bounds = data.count_bounds()
    reason = survey_counts(data.hists, *bounds).refusal(str(capture))
    if reason is not None:
        raise CaptureError(reason)
    return implausible(data.hists, *bounds)


def strongest_returns(counts: np.ndarray, sensor: SensorModel) -> tuple[np.ndarray, np.ndarray]:
    """(clear (V,) bool, range (V,) metres) of each view's strongest return, its zones summed: a view is clear when
    its peak stands 8 Poisson sigmas above the histogram's median (most bins hold background only) and lies between
    1 cm and the sensor's range. counts: (V, Z, B)."""
    h = counts.sum(axis=1)
    if sensor.ignore_bins:
        h[:, list(sensor.ignore_bins)] = 0.0
    floor = np.median(h, axis=1)
    peak = np.argmax(h, axis=1)
    clear = h[np.arange(len(h)), peak] > floor + 8 * np.sqrt(np.maximum(floor, 1.0))
    rng = sensor.range_of_bin(peak + 0.5)
    clear &= (rng > 0.01) & (rng < sensor.max_range_m)
    return clear, rng


def first_returns(counts: np.ndarray, poses: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """World points (n, 3) of each view's strongest return along its boresight, for views with a clear one
    (`strongest_returns`). counts: (V, Z, B)."""
    clear, rng = strongest_returns(counts, sensor)
    return poses[clear, :3, 3] + rng[clear, None] * poses[clear, :3, 2]


def _scene_sphere(scene: dict, poses: np.ndarray, points: np.ndarray, sensor: SensorModel, where: Path,
                  real: bool = False):
    """(centre (3,), radius, note) of a sphere that holds the object, from the manifest, else from the data; note
    (else None) says when views near the centre kept the sphere smaller than the first returns reach, the returns
    on a table (`_on_table`) left out: low views' returns from the table top far out are not the object's.

    `points`: the views' first returns (`first_returns`). Centre: the median of those points when at least 3 views
    show one (it lies inside the object for views from around it); else the point nearest to every boresight. Radius:
    3 x the 90th percentile of the points' distances to the centre, or FAR_RETURN_MARGIN x the farthest point's
    distance where that is more (at least 5 cm), never more than 0.8 x the nearest sensor's distance (no sensor
    inside); without points, 0.6 x that distance."""
    origins, axes = poses[:, :3, 3], poses[:, :3, 2]
    center, given_radius = given_sphere(scene, where)
    if center is None and len(points) >= 3:
        center = np.median(points, axis=0)
    elif center is None:
        # The point nearest to every boresight line: sum (I - d d^T) (x - o) = 0.
        proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
        a, b = proj.sum(0), np.einsum("nij,nj->i", proj, origins)
        if np.linalg.cond(a) < 1e6:
            center = np.linalg.solve(a, b)
        elif len(points):
            center = points.mean(0)
        else:
            center = (origins + axes * min(0.3, 0.5 * sensor.max_range_m)).mean(0)
    dist = np.linalg.norm(origins - center, axis=1)
    note = None
    if given_radius is not None:
        radius = given_radius
    elif len(points) >= 3:
        reach = np.linalg.norm(points - center, axis=1)
        spread, far = float(np.percentile(reach, 90)), float(reach.max())
        radius = min(RADIUS_FRACTION_MAX * float(dist.min()), max(3.0 * spread, FAR_RETURN_MARGIN * far, 0.05))
        beyond = float(np.mean((reach > radius) & ~_on_table(points, scene, real)))
        if beyond > BEYOND_BOUND_SHARE:
            # Nothing outside the sphere can be reconstructed: a scan from 0.2 m of a 0.2 m ball kept 60 % of it.
            note = bound_warning(float(dist.min()), radius, beyond)
    else:
        radius = RADIUS_FRACTION * float(dist.min())
    if radius < 1e-3:
        raise CaptureError(f"{where}: a sensor sits {dist.min() * 1e3:.1f} mm from the scene centre; cannot bound "
                           "the object (give scene.center and scene.radius in the manifest)")
    return center, radius, note


def _lowest_returns_z(points: np.ndarray) -> float:
    """The height (m) a fitted table starts at: the lowest first returns' (5th percentile of their heights)."""
    return float(np.percentile(points[:, 2], 5))


def _on_table(points: np.ndarray, scene: dict, real: bool) -> np.ndarray:
    """Which first-return points (n, 3) lie on the table top (within TABLE_RETURN_BAND_M of it) where the scene has
    one: a table the manifest places, else one to be fitted, whose top is taken at the lowest returns' height (5th
    percentile, where `_table` starts it). All False without a table."""
    spec = scene.get("table", True if real else None)
    if not spec or len(points) < 3:
        return np.zeros(len(points), dtype=bool)
    if spec is True:
        return points[:, 2] < _lowest_returns_z(points) + TABLE_RETURN_BAND_M
    try:
        plane = named_table(spec)
    except CaptureError:  # (`_table` names the malformed record)
        return np.zeros(len(points), dtype=bool)
    return np.abs(points @ plane.normal - plane.offset) < TABLE_RETURN_BAND_M


def _table(scene: dict, center: np.ndarray, radius: float, real: bool, points: np.ndarray,
           where: Path) -> TablePlane | None:
    """The table: as the manifest says; measured scenes that say nothing get a fitted horizontal table that starts
    at the lowest first returns (5th percentile of their heights), or the bottom of the scene sphere."""
    spec = scene.get("table", True if real else None)
    if not spec:
        return None
    if spec is True:
        start = _lowest_returns_z(points) if len(points) >= 3 else float(center[2] - radius)
        return TablePlane(np.array([0.0, 0.0, 1.0]), max(start, float(center[2] - radius)), fitted=True)
    try:
        return named_table(spec)
    except CaptureError as exc:
        raise CaptureError(f"{where / 'scan.json'}: {exc}") from None


def _background(counts, cycles, poses, center, radius, sensor: SensorModel, pulse_origin: int, real: bool):
    """(V, Z) background per bin per cycle, and where it came from.

    Simulated captures use the sensor model's value. Measured ones estimate it per histogram from the bins that end
    before any return can arrive (the scene sphere's nearest point, less the pulse's rise); with fewer than 3 such
    bins the sensor model's value is used. The estimate is floored at 1e-12 so that no rate is ever zero.
    """
    n_views, n_zones, n_bins = counts.shape
    fallback = np.full((n_views, n_zones), max(sensor.background, 1e-12))
    if not real:
        return fallback, "sensor model"
    near = np.maximum(np.linalg.norm(poses[:, :3, 3] - center, axis=1) - radius, 0.0)
    last = np.floor(sensor.bin_of_range(near) - pulse_origin - 1).astype(int)  # bins [0, last) are return-free
    bins = np.arange(n_bins)
    usable = bins[None] < last[:, None]
    if sensor.ignore_bins:
        usable[:, list(sensor.ignore_bins)] = False
    out, estimated = fallback.copy(), 0
    for v in range(n_views):
        idx = np.flatnonzero(usable[v])
        if idx.size >= 3:
            out[v] = np.maximum(counts[v][:, idx].mean(axis=1) / cycles[v], 1e-12)
            estimated += 1
    return out, "estimated" if estimated == n_views else ("sensor model" if estimated == 0 else "mixed")
