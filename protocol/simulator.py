"""The physically based simulator (docs/forward_model.md): mesh (and optionally a table) + sensor model + poses ->
photon-count histograms.

For each pose and zone, rays spread evenly over the zone's field of view find their first surface hit by ray casting.
A hit at one-way range r with incidence cosine cos_i adds

    signal_scale * power * albedo * weight * cos_i / r^2        (weight: the ray's solid angle, steradians)

photons per cycle, arriving at bin coordinate zero_bin + r / bin_width. With a table (sim_table.py), a ray that
meets the table before the mesh returns from the table, with the table's albedo. The returns are convolved with the
laser pulse on an oversampled axis and integrated back to bins, scaled by zone gains, mixed by crosstalk (each zone
also gets `crosstalk` x the sum of all zones' signal) and lifted by a flat background. Coates pile-up turns these
rates into per-cycle detection probabilities, timing jitter blurs them, and N cycles give multinomial counts
(detections per bin plus a "no photon" outcome), clipped to the sensor's counter size.

Rules at the edges: a surface closer than MIN_RANGE_M counts as if it were at MIN_RANGE_M (finite, saturating flux at
the start of the histogram); returns whose pulse cannot reach the histogram (far beyond the last bin, or well before
bin 0) add nothing; the background never drops below BACKGROUND_FLOOR so that likelihoods never see a zero rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import pileup
from .errors import SimulationError
from .raycast import first_hits, make_intersector, zone_rays
from .sensor_model import MAX_SIGNAL_SCALE, SensorModel
from .sim_table import SimTable
from .transient import FineAxis, convolve_pulse, pulse_pad_bins

MIN_RANGE_M = 1e-3
"""Surfaces closer than this (metres) are treated as being at this range."""
BACKGROUND_FLOOR = 1e-12
"""Smallest background rate (photons per bin per cycle) used in the rates, so that no bin has rate zero."""
RAYS_PER_VIEW = 4096
"""Default ray budget per pose, shared by the zones."""
MIN_RAYS_PER_ZONE = 512
"""Fewest rays per zone the default gives."""
REFERENCE_STRETCH = 1.10
REFERENCE_POWER = 1.5
"""The measured mapping from a reference histogram to the zones' pulse (docs/sensor_models.md):
p(t) = [ref_n(ref_peak + (t - pulse_peak) / REFERENCE_STRETCH)] ** REFERENCE_POWER. The simulator draws its reference
from the inverse, so that whoever derives the pulse from a simulated reference (as from a measured one) gets the
sensor model's pulse back."""
_RAYS_PER_BLOCK = 1 << 20  # rays cast per intersector call: bounds memory, amortises call overhead


@dataclass(frozen=True)
class SimSettings:
    """Photon settings of a simulation; `None` takes the sensor model's own value."""

    power: float = 1.0
    """Multiplies the sensor's signal_scale (laser power relative to the model)."""
    ambient: float | None = None
    """Background photons per bin per cycle (sunlight, room light); None = the sensor model's background."""
    cycles: int | None = None
    """Laser cycles per histogram; None = the sensor model's cycles."""
    albedo: float = 1.0
    """Lambertian albedo of every surface of the mesh (relative to the sensor model's signal_scale)."""
    rays_per_zone: int | None = None
    """Rays cast per zone per pose; None = RAYS_PER_VIEW shared by the zones, at least MIN_RAYS_PER_ZONE each
    (lcspc-sim: 4096, per-view totals within 0.7% and shapes within 0.4% (L1) of 65536 rays on the bunny;
    tmf8820: 512 per zone)."""
    oversample: int = 8
    """Fine time cells per bin used to place returns with sub-bin accuracy before integrating to bins."""
    reference_signal: float = 0.06
    """Detections per cycle of the reference channel's pulse (sensors with one) at power 1, which scales it as it
    scales the zones' returns; its counts over the cycles: ~0.06 on the real TMF8820 (~2.3e5 counts over ~4e6
    cycles)."""
    reference_background: float = 1.0e-6
    """Flat background of the reference channel, detections per bin per cycle (~4 counts over ~4e6 cycles)."""
    reference_delay_bins: float = 2.37
    """The reference's peak lies this many bins after the zones' zero-range point (internal optical path): the real
    TMF8820's reference peaks at bin index 14.27 (bin coordinate 14.77, bin i centred at i + 0.5), its zones'
    zero-range point at bin coordinate 12.40."""

    def check(self) -> "SimSettings":
        for key, lo, hi in (("power", 0.0, 1e9), ("albedo", 0.0, 1e3), ("reference_signal", 0.0, 1e6),
                            ("reference_background", 0.0, 1.0), ("reference_delay_bins", -1e4, 1e4)):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise SimulationError(f"{key} = {v} is outside [{lo}, {hi}]")
        if self.ambient is not None and not (math.isfinite(self.ambient) and 0 <= self.ambient <= 1.0):
            raise SimulationError(f"ambient {self.ambient} photons/bin/cycle is outside [0, 1]")
        if self.cycles is not None and not (isinstance(self.cycles, (int, np.integer)) and 1 <= self.cycles <= 10**10):
            raise SimulationError(f"cycles {self.cycles} must be an integer in [1, 1e10]")
        if self.rays_per_zone is not None and not (
                isinstance(self.rays_per_zone, (int, np.integer)) and 1 <= self.rays_per_zone <= 10_000_000):
            raise SimulationError(f"rays per zone {self.rays_per_zone} must be an integer in [1, 1e7]")
        if not (isinstance(self.oversample, (int, np.integer)) and 1 <= self.oversample <= 64):
            raise SimulationError(f"oversample {self.oversample} must be an integer in [1, 64]")
        return self


@dataclass
class SimFrames:
    """Simulated measurements. hists: (n, zones, bins) uint32 counts; reference: (n, bins) uint32 or None;
    poses: (n, 4, 4) float64 sensor-to-world (metres); misses: (n, zones) int64 cycles that detected nothing in
    the histogram window (before clipping to max_count, hists.sum(-1) + misses == cycles); signal_photons: (n,)
    float64 expected signal photons of each view, all zones and cycles (before pile-up; 0: it sees nothing; the
    table's included); mesh_photons: (n,) float64 the part of signal_photons that returns from the mesh."""

    hists: np.ndarray
    reference: np.ndarray | None
    poses: np.ndarray
    misses: np.ndarray | None = None
    signal_photons: np.ndarray | None = None
    mesh_photons: np.ndarray | None = None


def check_seed(seed) -> int:
    """The seed as an int; one-line SimulationError unless it is an integer >= 0 (what numpy's SeedSequence takes)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SimulationError(f"seed {seed!r} must be an integer >= 0")
    return int(seed)


def check_pose_array(poses) -> np.ndarray:
    """Poses as (n, 4, 4) float64 rigid transforms; one-line SimulationError otherwise."""
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] != (4, 4):
        raise SimulationError(f"poses must have shape (n, 4, 4), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise SimulationError("poses hold non-finite values")
    rot = p[:, :3, :3]
    err = np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).reshape(len(p), 9).max(axis=1, initial=0.0)
    bad = np.flatnonzero((err > 1e-4) | (np.linalg.det(rot) < 0) | np.any(p[:, 3] != [0, 0, 0, 1], axis=1))
    if bad.size:
        raise SimulationError(f"pose {bad[0]} is not a rigid transform (rotation off orthonormal by {err[bad[0]]:.2g})")
    return p


class Simulator:
    """Renders one mesh for one sensor model; build once, render any poses (one at a time or thousands).

    `sensor` is the model the histograms obey: the given model with the settings' power, ambient and cycles folded in
    (store it with the capture). `expected_rates` and `transient` are pure functions of the poses; `frames` draws
    photons from a generator seeded by `seed`, so the same calls in the same order give the same counts. The
    reference histograms draw from a generator of their own, so that the zones' counts do not depend on them.
    """

    def __init__(self, mesh, sensor: SensorModel, settings: SimSettings = SimSettings(), seed: int = 0,
                 table: SimTable | None = None):
        settings.check()
        self.table = None if table is None else table.check()
        check_seed(seed)
        sensor.validate()
        faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
        if len(faces) == 0:
            raise SimulationError("mesh has no triangles")
        if not np.all(np.isfinite(mesh.vertices)):
            raise SimulationError("mesh has non-finite vertices")
        if sensor.signal_scale * settings.power > MAX_SIGNAL_SCALE:
            raise SimulationError(f"power = {settings.power:g} is too much for sensor {sensor.name!r}: at most "
                                  f"{MAX_SIGNAL_SCALE / sensor.signal_scale:.4g} (its signal scale is "
                                  f"{sensor.signal_scale:g})")
        self.settings = settings
        self.base_sensor = sensor
        self.sensor = sensor.with_(
            signal_scale=sensor.signal_scale * settings.power,
            background=sensor.background if settings.ambient is None else float(settings.ambient),
            cycles=sensor.cycles if settings.cycles is None else int(settings.cycles),
        )
        self.mesh = mesh
        self._intersector = make_intersector(mesh)
        # The third child leaves the first two (and so the rays and the zones' counts) as they were with two.
        ray_seed, photon_seed, reference_seed = np.random.SeedSequence(int(seed)).spawn(3)
        self.rays_per_zone = int(settings.rays_per_zone or max(MIN_RAYS_PER_ZONE, RAYS_PER_VIEW // sensor.n_zones))
        self.rays = zone_rays(sensor.zones, self.rays_per_zone, int(ray_seed.generate_state(1)[0]))
        self.rng = np.random.default_rng(photon_seed)
        self.reference_rng = np.random.default_rng(reference_seed)
        self._kernel, self._origin = sensor.pulse.kernel(settings.oversample)
        self.axis = FineAxis(sensor.n_bins, settings.oversample,
                             pulse_pad_bins(self._kernel, self._origin, settings.oversample))

    # ---- geometry ------------------------------------------------------------------------------------------------
    def _returns(self, poses: np.ndarray):
        """Ray-cast every zone's rays from every pose.

        Returns (channel (H,), t_bins (H,), value (H,), from_mesh (H,) bool): histogram index view * zones + zone,
        arrival bin coordinate, albedo * weight * cos_i / r^2 (sr / m^2), and whether the return is the mesh's (not
        the table's).
        """
        z, r = self.rays.directions.shape[:2]
        per_view = z * r
        block = max(1, _RAYS_PER_BLOCK // per_view)
        out = []
        for start in range(0, len(poses), block):
            p = poses[start: start + block]
            dirs = np.matmul(self.rays.directions.reshape(1, -1, 3), p[:, :3, :3].transpose(0, 2, 1)).reshape(-1, 3)
            origins = np.repeat(p[:, :3, 3], per_view, axis=0)
            ray, rng_m, cos_i = first_hits(self._intersector, self.mesh, origins, dirs)
            albedo = np.full(len(ray), self.settings.albedo)
            from_mesh = np.ones(len(ray), bool)
            if self.table is not None:
                ray, rng_m, cos_i, albedo, from_mesh = self._with_table(origins, dirs, ray, rng_m, cos_i, albedo)
            rng_m = np.maximum(rng_m, MIN_RANGE_M)
            w = self.rays.weights.reshape(-1)[ray % per_view]
            channel = start * z + ray // r
            out.append((channel, self.sensor.bin_of_range(rng_m), albedo * w * cos_i / (rng_m * rng_m), from_mesh))
        if not out:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0, bool)
        return tuple(np.concatenate(parts) for parts in zip(*out))

    def _with_table(self, origins, dirs, ray, rng_m, cos_i, albedo):
        """The mesh's first hits (ray, range, cos, albedo) merged with the table's: each ray returns from whichever
        it meets first. Returns them with from_mesh, False for the table's."""
        t_table, cos_table = self.table.hits(origins, dirs)
        mesh_first = rng_m <= t_table[ray]
        ray, rng_m, cos_i, albedo = ray[mesh_first], rng_m[mesh_first], cos_i[mesh_first], albedo[mesh_first]
        on_table = np.isfinite(t_table)
        on_table[ray] = False
        hit = np.flatnonzero(on_table)
        return (np.concatenate([ray, hit]), np.concatenate([rng_m, t_table[hit]]),
                np.concatenate([cos_i, cos_table[hit]]), np.concatenate([albedo, np.full(len(hit), self.table.albedo)]),
                np.concatenate([np.ones(len(ray), bool), np.zeros(len(hit), bool)]))

    def transient(self, poses) -> np.ndarray:
        """Ideal transient h: albedo x integral of cos_i / r^2 dOmega per bin (sr/m^2), no pulse, gains or noise.

        poses (n, 4, 4) -> (n, zones, bins) float64; a return at bin coordinate t counts in bin floor(t) (to within
        one fine cell).
        """
        poses = check_pose_array(poses)
        n, z = len(poses), self.sensor.n_zones
        channel, t, value, _ = self._returns(poses)
        fine = self.axis.splat(channel, t, value, n * z)
        return self.axis.to_bins(fine).reshape(n, z, self.sensor.n_bins)

    def signal_rates(self, poses) -> np.ndarray:
        """Signal photons per bin per cycle (pulse, gains, crosstalk; no background). (n, 4, 4) -> (n, zones, bins)."""
        poses = check_pose_array(poses)
        channel, t, value, _ = self._returns(poses)
        return self._signal(len(poses), channel, t, value)

    def _signal(self, n: int, channel, t, value) -> np.ndarray:
        """Signal rates (n, zones, bins) of n views from their returns (see `_returns`)."""
        z = self.sensor.n_zones
        fine = self.axis.splat(channel, t, value * self.sensor.signal_scale, n * z)
        sig = self.axis.to_bins(convolve_pulse(fine, self._kernel, self._origin)).reshape(n, z, self.sensor.n_bins)
        sig *= np.array([zone.gain for zone in self.sensor.zones])[:, None]
        if self.sensor.crosstalk > 0:
            sig += self.sensor.crosstalk * sig.sum(axis=1, keepdims=True)
        return sig

    def expected_rates(self, poses) -> np.ndarray:
        """Photon rate lambda per bin per cycle before pile-up: signal + background. (n, 4, 4) -> (n, zones, bins)."""
        return self.signal_rates(poses) + max(self.sensor.background, BACKGROUND_FLOOR)

    def reference_rates(self, n: int) -> np.ndarray | None:
        """Rates of the reference channel (n, bins), or None when the sensor has none.

        The real TMF8820's reference is not the zones' pulse: it is wider in its tail, and the zones' pulse is the
        reference mapped by REFERENCE_STRETCH and REFERENCE_POWER. So the reference's expected counts are the
        sensor's pulse mapped back (`reference_shape`), peaking reference_delay_bins after the zero-range point,
        over a flat background; the rates are those counts with the pile-up undone, so that the counts drawn from
        them (pile-up applied) have that shape, as the measured reference (counts) does."""
        if not self.sensor.has_reference:
            return None
        kernel, origin = self.sensor.pulse.kernel(1)
        peak_index = self.sensor.zero_bin + self.settings.reference_delay_bins - 0.5  # bin i is centred at i + 0.5
        # The reference sees the same laser through its internal path: a stronger or weaker emitter (power) scales it
        # as it scales the zones' returns.
        signal = self.settings.reference_signal * self.settings.power
        per_cycle = signal * reference_shape(kernel, int(origin), self.sensor.n_bins, peak_index)
        per_cycle = per_cycle + max(self.settings.reference_background, BACKGROUND_FLOOR)
        if self.sensor.pileup:
            cycles = float(self.sensor.cycles)
            ref = pileup.coates_correct(per_cycle * cycles, cycles)
        else:
            ref = per_cycle
        return np.broadcast_to(ref, (n, ref.size)).copy()

    # ---- photons -------------------------------------------------------------------------------------------------
    def detection_probabilities(self, rates: np.ndarray) -> np.ndarray:
        """Per-cycle probability of a detection in each bin (pile-up and jitter as the sensor says), (..., bins)."""
        if self.sensor.pileup:
            p = pileup.detection_probabilities(rates)
        else:
            p = pileup.detection_probabilities_no_pileup(rates)
        return pileup.jitter_blur(p, self.sensor.jitter_bins)

    def draw_counts(self, rates: np.ndarray, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Photon counts over the sensor's cycles for rates (..., bins), drawn from `rng` (default: the zones').

        Returns (counts (..., bins) uint32 clipped to max_count, misses (...) int64 cycles without a detection).
        Without pile-up every photon counts (Poisson per bin) and misses are cycles minus counts, floored at 0.
        """
        rng = self.rng if rng is None else rng
        n_cycles = self.sensor.cycles
        p = self.detection_probabilities(rates)
        if self.sensor.pileup:
            total = p.sum(axis=-1, keepdims=True)
            p = p / np.maximum(total, 1.0) * (1.0 - 1e-12)  # the "no photon" outcome takes the rest, never < 0
            pvals = np.concatenate([p, 1.0 - p.sum(axis=-1, keepdims=True)], axis=-1)
            drawn = rng.multinomial(n_cycles, pvals)
            counts, misses = drawn[..., :-1], drawn[..., -1]
        else:
            counts = rng.poisson(np.minimum(p * n_cycles, 1e15))
            misses = np.maximum(n_cycles - counts.sum(axis=-1), 0)
        return np.minimum(counts, self.sensor.max_count).astype(np.uint32), misses.astype(np.int64)

    def frames(self, poses) -> SimFrames:
        """Photon-count histograms for poses (n, 4, 4); advances the generator (deterministic for the seed)."""
        poses = check_pose_array(poses)
        channel, t, value, from_mesh = self._returns(poses)
        signal = self._signal(len(poses), channel, t, value)
        hists, misses = self.draw_counts(signal + max(self.sensor.background, BACKGROUND_FLOOR))
        ref = self.reference_rates(len(poses))
        photons = signal.sum(axis=(1, 2)) * self.sensor.cycles
        mesh_photons = photons
        if self.table is not None:  # the table's returns say nothing of whether a view sees the object
            mesh_signal = self._signal(len(poses), channel[from_mesh], t[from_mesh], value[from_mesh])
            mesh_photons = mesh_signal.sum(axis=(1, 2)) * self.sensor.cycles
        reference = None if ref is None else self.draw_counts(ref, self.reference_rng)[0]
        return SimFrames(hists, reference, poses.copy(), misses, photons, mesh_photons)


def reference_shape(kernel: np.ndarray, origin: int, n_bins: int, peak_index: float) -> np.ndarray:
    """The reference histogram's shape (n_bins,), summing to 1, of a sensor whose zones' pulse is `kernel` (per bin,
    kernel[origin] at the arrival): the documented mapping from reference to pulse (docs/sensor_models.md) run
    backwards, ref_n(u) = p(REFERENCE_STRETCH * (u - peak_index)) ** (1 / REFERENCE_POWER), with p the kernel
    interpolated linearly between bins and u a bin index (peak_index too: bin i's value stands at u = i)."""
    k = np.asarray(kernel, np.float64)
    p = np.interp(REFERENCE_STRETCH * (np.arange(n_bins) - float(peak_index)), np.arange(k.size) - int(origin),
                  k / k.max(), left=0.0, right=0.0)
    shape = p ** (1.0 / REFERENCE_POWER)
    total = shape.sum()
    if total <= 0:
        raise SimulationError(f"the reference's peak at bin {peak_index:.3g} leaves the {n_bins}-bin histogram")
    return shape / total


def simulate_capture(mesh, sensor: SensorModel, poses, out, *, settings: SimSettings = SimSettings(), seed: int = 0,
                     chunk_size: int = 64, scene: dict | None = None, schedule: dict | None = None,
                     progress: bool = True, log=None, table: SimTable | None = None, refuse_misplaced: bool = False):
    """Render `poses` (n, 4, 4) of `mesh` (on `table`, if given) into a complete capture folder `out` (which must not
    hold a capture).

    The manifest records the effective sensor model (settings folded in), `scene` (plus the albedo) and `schedule`.
    A table is recorded as a measured capture's is to the reconstruction, `"table": true` (there is one, its height is
    to be found), and in full as `"simulated_table"` (its height `z`, `albedo` and `half_size_m`) for scoring.
    Shows a progress bar on stderr unless `progress` is False. Views that put the sensor inside the mesh or under the
    table (`misplaced_views_note`) raise SimulationError before anything is written when `refuse_misplaced` (as
    `spadscan simulate` and a sweep's points do), else `log` (a function of one line) hears of them: a library caller
    may render them on purpose. `log` hears of views that see nothing of the mesh too (`blind_views_note`).
    Returns the capture's path.
    """
    from pathlib import Path

    from tqdm import tqdm

    from .capture_format import Measurement
    from .capture_writer import CaptureWriter

    poses = check_pose_array(poses)
    sim = Simulator(mesh, sensor, settings, seed, table)
    misplaced = misplaced_views_note(poses, mesh, sim.table)
    if misplaced and refuse_misplaced:
        raise SimulationError(misplaced)
    if misplaced and log is not None:
        log(f"warning: {misplaced}")
    scene = {**(scene or {}), "albedo": settings.albedo, "seed": int(seed), "rays_per_zone": sim.rays.n_rays,
             "faces": int(len(mesh.faces))}
    if table is not None:
        scene.update(table=True, simulated_table=table.record())
    writer = CaptureWriter.create(Path(out), sim.sensor, rig={"kind": "simulated"}, schedule=schedule or {},
                                  planned_poses=poses, chunk_size=chunk_size, scene=scene)
    photons = []
    try:
        with tqdm(total=len(poses), desc="simulate", unit="view", disable=not progress, leave=False) as bar:
            for start in range(0, len(poses), chunk_size):
                fr = sim.frames(poses[start: start + chunk_size])
                photons.append(fr.mesh_photons)
                for i in range(len(fr.poses)):
                    ref = None if fr.reference is None else fr.reference[i]
                    writer.append(Measurement(fr.hists[i], fr.poses[i], start + i, 0, ref, {"simulated": True}))
                writer.flush()
                bar.update(len(fr.poses))
        writer.finish("complete")
    except BaseException as exc:
        # A simulation cannot be resumed: say in the manifest that this one stopped part-way, and why.
        writer.abandon("simulation", exc)
        raise
    note = blind_views_note(np.concatenate(photons), mesh)
    if note and log is not None:
        log(note)
    return writer.path


def misplaced_views(poses, mesh, table: SimTable | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(inside (n,), under (n,)) bool: which views of poses (n, 4, 4) put the sensor inside `mesh` (a watertight one:
    an open mesh has no inside), and which on or under the `table`'s top (see SimTable.below_top). No sensor can
    stand at either place, and what it renders there is no capture a rig could take: the inner wall of the object,
    the table's underside, or a table top met at range 0 (a hair above it, at a grazing angle that floods the
    histograms)."""
    origins = check_pose_array(poses)[:, :3, 3]
    inside = np.zeros(len(origins), bool)
    if len(origins) and getattr(mesh, "is_watertight", False):
        inside = np.asarray(mesh.contains(origins), bool)
    under = np.zeros(len(origins), bool) if table is None else table.below_top(origins)
    return inside, under


FLOODED_BINS = 4
"""The first bins of a histogram, at least (`flooded_bins`): most of its detections there say pile-up (the first
photon of nearly every cycle comes at once: a surface touching the sensor, or so much ambient light or laser power
that the sensor fills its first bins and sees nothing behind them)."""
FLOODED_SHARE = 0.5
"""A histogram holding more than this share of its detections in its first `flooded_bins` bins is flooded."""


def flooded_bins(sensor: SensorModel) -> int:
    """How many first bins of `sensor`'s histograms a flooded one fills: those before zero range and the one that
    holds it, at least FLOODED_BINS. A sensor whose zero range lies far into its histogram (the TMF8820's at bin
    12.4, its pulse peaking 3 bins before it) puts the return of a surface touching it there, not in bins 0-3: counted
    from bin 0 alone, a TMF8820 capture whose every view touched the sphere was written without a word."""
    return min(sensor.n_bins, max(FLOODED_BINS, math.ceil(sensor.zero_bin) + 1))


def flooded_note(hists: np.ndarray, sensor: SensorModel) -> str | None:
    """A warning for a capture whose views are mostly flooded (`FLOODED_SHARE` of a histogram's detections in its
    first `flooded_bins` bins, for most of a view's zones, in most views), or None. hists (n, zones, bins) counts of
    `sensor`; the bins it ignores (the TMF8820's reference bin 0) are left out."""
    h = np.array(hists, dtype=np.float64)
    h[..., [b for b in sensor.ignore_bins if b < h.shape[-1]]] = 0.0
    first = flooded_bins(sensor)
    total = h.sum(axis=-1)
    early = h[..., :first].sum(axis=-1)
    flooded = (total > 0) & (early > FLOODED_SHARE * total)
    views = flooded.mean(axis=1) > 0.5
    if views.mean() <= 0.5:
        return None
    share = float(early[flooded].sum() / total[flooded].sum())
    return (f"warning: {int(views.sum())} of {len(views)} views hold {100 * share:.0f} % of their detections in "
            f"their first {first} bins (pile-up: a surface touching the sensor, or so much ambient light or "
            f"laser power that the first photon of nearly every cycle comes at once): they show no return behind "
            f"it, and reconstruct will refuse or misread them; move the views back, or lower --ambient / --power")


def saturated_note(hists: np.ndarray) -> str | None:
    """A warning for a capture most of whose histograms are saturated (`pileup.saturated_histograms`: the first
    return stopped nearly every laser cycle), or None. hists (n, zones, bins) counts. A flooded capture
    (`flooded_note`) is not said again here: its returns in the first bins leave nothing before them to judge."""
    saturated, judged = pileup.saturated_count(hists)
    if not pileup.mostly_saturated(saturated, judged):
        return None
    return (f"warning: {saturated} of {judged} histograms are saturated (pile-up: their first "
            f"return stopped nearly every laser cycle, so they hold only the leading edge of each view's nearest "
            f"surface and nothing behind it): reconstruct will fit them poorly and say so; lower --power or "
            f"--ambient, or move the views back")


def misplaced_views_note(poses, mesh, table: SimTable | None = None) -> str | None:
    """A line naming how many views, and which, put the sensor inside the mesh or on or under the table top (see
    `misplaced_views`); None when none does."""
    inside, under = misplaced_views(poses, mesh, table)
    n = len(inside)
    parts = []
    if inside.any():
        parts.append(f"{_views(inside, n)} inside the mesh")
    if under.any():
        parts.append(f"{_views(under, n)} on or under the table top (z = {table.height_m:g} m)")
    if not parts:
        return None
    return (f"{' and '.join(parts)}: no sensor can stand there; move the target or the radius (metres), or the "
            f"elevations")


def _views(which: np.ndarray, n: int, shown: int = 8) -> str:
    """'3 of 32 views (0, 1, 2) put the sensor' for a mask of views; the first `shown` indices, then '...'."""
    idx = np.flatnonzero(which)
    listed = ", ".join(str(i) for i in idx[:shown]) + (", ..." if len(idx) > shown else "")
    return f"{len(idx)} of {n} views ({listed}) put the sensor"


MIN_SIGNAL_PHOTONS = 1.0
"""A view whose histograms expect fewer signal photons than this (all zones and cycles) holds background alone."""


def blind_views_note(signal_photons: np.ndarray, mesh) -> str | None:
    """A line saying how many views see nothing of `mesh` (fewer than MIN_SIGNAL_PHOTONS signal photons expected
    from the mesh itself: a table's returns do not count), with the mesh's bounds to compare with the schedule's
    target and radius; None when every view sees it. Such views hold background (and table) alone: a mesh placed
    away from the target, or a schedule that looks past it."""
    blind = int(np.count_nonzero(np.asarray(signal_photons) < MIN_SIGNAL_PHOTONS))
    if blind == 0:
        return None
    lo, hi = (np.round(b, 3).tolist() for b in mesh.bounds)
    n = len(signal_photons)
    which = f"none of the {n} views see the mesh" if blind == n else f"{blind} of {n} views see nothing of the mesh"
    return (f"warning: {which} (under {MIN_SIGNAL_PHOTONS:g} signal photon expected); the mesh lies within {lo} .. "
            f"{hi} m: check the target and radius (or the albedo and power)")


__all__ = ["SimSettings", "SimFrames", "SimTable", "Simulator", "simulate_capture", "blind_views_note", "flooded_note",
           "flooded_bins", "saturated_note", "reference_shape", "misplaced_views", "misplaced_views_note",
           "check_pose_array", "check_seed", "MIN_RANGE_M", "BACKGROUND_FLOOR", "MIN_SIGNAL_PHOTONS",
           "REFERENCE_STRETCH", "REFERENCE_POWER"]
