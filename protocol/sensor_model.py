"""The sensor model: one record that says what a transient histogram means.

It is stored in every capture (`scan.json`) and read back by the worker, so it is plain data with a JSON form that is
validated on load. Units: metres and radians inside; a *bin coordinate* t means bin i covers [i, i + 1).

A return from a surface at one-way range r (metres) arrives at bin coordinate `zero_bin + r / bin_width_m`; the
laser pulse (kernel sampled per bin, normalised to sum 1) is placed there, then pile-up and noise act on the rate.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import MISSING, asdict, dataclass, fields, replace

import numpy as np

from .errors import SensorModelError

MAX_SIGNAL_SCALE = 1e9
"""The largest signal_scale a sensor model may state (photons per cycle per unit albedo per sr/m^2: far beyond any
sensor's saturation)."""
MAX_RECT_TAN = 2.0
"""A rectangular zone's edges lie within |tan| < this (63.4 degrees off the sensor's axis: a zone 127 degrees wide,
wider than any single-photon sensor's whole field). Its rays are spread evenly in tangent (raycast.rect_rays), so a
wider zone leaves its centre to a few of them: at |tan| 9.9 and 4,096 rays, a 10 cm box half a metre away was hit
whole at one seed and missed at another."""


@dataclass(frozen=True)
class Zone:
    """Where one zone (one histogram channel) looks, in the sensor frame (+z is the boresight).

    A `cone` zone sees every direction within `half_angle_rad` of `axis`; a `rect` zone sees directions whose
    tan(x/z) lies in `tan_x` and tan(y/z) in `tan_y` (the TMF8820's rectangular SPAD zones).
    """

    kind: str = "cone"
    """'cone' or 'rect'."""
    half_angle_rad: float = 0.0
    """Cone half-angle (radians); cone zones only."""
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """Cone axis, unit vector in the sensor frame; cone zones only."""
    tan_x: tuple[float, float] = (0.0, 0.0)
    """(low, high) bounds of x/z; rect zones only."""
    tan_y: tuple[float, float] = (0.0, 0.0)
    """(low, high) bounds of y/z; rect zones only."""
    gain: float = 1.0
    """Relative sensitivity of this zone (emitter pattern, SPAD count); 1 for the reference zone."""

    def validate(self, where: str) -> None:
        _check_types(self, {"kind": "string", "half_angle_rad": "number", "axis": "numbers", "tan_x": "numbers",
                            "tan_y": "numbers", "gain": "number"}, where)
        if self.kind == "cone":
            if not 0.0 < self.half_angle_rad < math.pi / 2:
                raise SensorModelError(f"{where}: cone half-angle {self.half_angle_rad} rad is outside (0, pi/2)")
            n = np.asarray(self.axis, float)
            if n.shape != (3,) or not np.all(np.isfinite(n)) or abs(np.linalg.norm(n) - 1) > 1e-6 or n[2] <= 0:
                raise SensorModelError(f"{where}: cone axis {self.axis} must be a forward-looking unit 3-vector")
        elif self.kind == "rect":
            for name, (lo, hi) in (("tan_x", self.tan_x), ("tan_y", self.tan_y)):
                if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                    raise SensorModelError(f"{where}: {name} bounds ({lo}, {hi}) must be finite with low < high")
                if not (abs(lo) < MAX_RECT_TAN and abs(hi) < MAX_RECT_TAN):
                    raise SensorModelError(
                        f"{where}: {name} bounds ({lo}, {hi}) must lie within |tan| < {MAX_RECT_TAN:g} (edges under "
                        f"{math.degrees(math.atan(MAX_RECT_TAN)):.1f} degrees off the axis): the rays of a wider zone "
                        f"leave its centre to a few of them")
        else:
            raise SensorModelError(f"{where}: zone kind {self.kind!r} is not 'cone' or 'rect'")
        if not (math.isfinite(self.gain) and self.gain > 0):
            raise SensorModelError(f"{where}: gain {self.gain} must be positive")

    def holds(self, rel):
        """(...) bool: whether sensor-frame points or directions `rel` (..., 3) lie in the zone's field of view.

        Elementwise arithmetic only, so `rel` may be a numpy array or a torch tensor (on any device) and the result is
        of the same kind: the fit's parts and the view planner share this one test."""
        if self.kind == "rect":
            return self.holds_tangents(*front_tangents(rel))
        x, y, z = rel[..., 0], rel[..., 1], rel[..., 2]
        length = (x * x + y * y + z * z) ** 0.5
        dot = x * self.axis[0] + y * self.axis[1] + z * self.axis[2]
        return dot >= math.cos(self.half_angle_rad) * (length + 1e-12)

    def holds_tangents(self, front, tx, ty):
        """`holds` for a rect zone, from `front_tangents` of the points (shared by every rect zone of a sensor)."""
        return front & (tx >= self.tan_x[0]) & (tx <= self.tan_x[1]) & (ty >= self.tan_y[0]) & (ty <= self.tan_y[1])

    def solid_angle_sr(self) -> float:
        """Solid angle of the zone (steradians)."""
        if self.kind == "cone":
            # 1 - cos(a) written as 2 sin^2(a / 2): the difference underflows to 0 below about 1e-8 rad, and a zone
            # of no solid angle weighs its rays 0 / 0.
            return 4 * math.pi * math.sin(self.half_angle_rad / 2) ** 2
        # Solid angle of a rectangle on the z = 1 plane: sum of signed corner terms atan(xy / sqrt(1 + x^2 + y^2)).
        total = 0.0
        for x, sx in ((self.tan_x[1], 1), (self.tan_x[0], -1)):
            for y, sy in ((self.tan_y[1], 1), (self.tan_y[0], -1)):
                total += sx * sy * math.atan(x * y / math.sqrt(1 + x * x + y * y))
        return total


def front_tangents(rel):
    """(front, tx, ty) of sensor-frame points or directions `rel` (..., 3): whether each lies in front of the sensor
    (z > 0), and x/z, y/z there (x and y behind it, where `front` rules them out: no division by zero). Numpy or
    torch alike."""
    x, y, z = rel[..., 0], rel[..., 1], rel[..., 2]
    front = z > 1e-9
    tz = z * front + ~front  # z where in front, 1 elsewhere
    return front, x / tz, y / tz


def zone_masks(zones, rel) -> list:
    """[(...) bool for each of `zones`]: `Zone.holds` of `rel` (..., 3), with the rect zones' tangents computed once
    for all of them (a TMF8820's nine zones cost one division, not nine)."""
    tangents = None
    masks = []
    for zone in zones:
        if zone.kind == "rect":
            tangents = front_tangents(rel) if tangents is None else tangents
            masks.append(zone.holds_tangents(*tangents))
        else:
            masks.append(zone.holds(rel))
    return masks


def in_any_zone(zones, rel):
    """(...) bool: whether sensor-frame points or directions `rel` (..., 3) lie in the field of view of any of `zones`
    (a sensor model's, never empty), numpy or torch alike as `Zone.holds`."""
    seen = None
    for held in zone_masks(zones, rel):
        seen = held if seen is None else seen | held
    return seen


@dataclass(frozen=True)
class Pulse:
    """The laser impulse response as seen by the detector, per bin.

    `kind='exgauss'`: a Gaussian (sigma_bins) convolved with a one-sided exponential tail (tau_bins), its Gaussian
    centre at the arrival time. `kind='table'`: `values[k]` is the share of a return arriving at a bin's centre that
    falls k - origin bins after that bin.
    """

    kind: str = "exgauss"
    sigma_bins: float = 1.0
    tau_bins: float = 0.0
    values: tuple[float, ...] = ()
    origin: int = 0

    def validate(self, where: str) -> None:
        _check_types(self, {"kind": "string", "sigma_bins": "number", "tau_bins": "number", "values": "numbers",
                            "origin": "integer"}, where)
        if self.kind == "exgauss":
            if not (math.isfinite(self.sigma_bins) and 0.05 <= self.sigma_bins <= 1000):
                raise SensorModelError(f"{where}: pulse sigma {self.sigma_bins} bins is outside [0.05, 1000]")
            if not (math.isfinite(self.tau_bins) and 0 <= self.tau_bins <= 1000):
                raise SensorModelError(f"{where}: pulse tail tau {self.tau_bins} bins is outside [0, 1000]")
        elif self.kind == "table":
            v = np.asarray(self.values, float)
            if v.ndim != 1 or v.size == 0 or not np.all(np.isfinite(v)) or np.any(v < 0) or v.sum() <= 0:
                raise SensorModelError(f"{where}: pulse table must be a non-empty list of finite values >= 0")
            if not 0 <= self.origin < v.size:
                raise SensorModelError(f"{where}: pulse origin {self.origin} is outside the table (0..{v.size - 1})")
        else:
            raise SensorModelError(f"{where}: pulse kind {self.kind!r} is not 'exgauss' or 'table'")

    def kernel(self, oversample: int = 1) -> tuple[np.ndarray, int]:
        """The pulse sampled every 1/oversample bins, normalised to sum 1, and the index of the arrival time.

        Returns (kernel (K,), origin) with kernel[origin + k] the response k/oversample bins after arrival.
        """
        if self.kind == "table":
            # Each bin's value spread evenly over its `oversample` cells, the arrival in the middle of its bin's
            # block: binned back, a return gives the table (a return at a bin's centre: the table to 2 %) and the
            # same mean response over arrival positions at any oversampling. Linear interpolation of the values as
            # point samples blurred it: the peak bin's share fell 10 % from oversample 1 (the fast preset) to 8
            # (the simulator), which rendered another pulse than the one the reconstruction fits.
            v = np.repeat(np.asarray(self.values, float), oversample)
            if oversample % 2 == 0:  # an even block has no middle cell: half cells at both ends centre it
                v = np.convolve(v, [0.5, 0.5])
            return v / v.sum(), self.origin * oversample + oversample // 2
        s, tau = self.sigma_bins, self.tau_bins
        # Sample finely, convolve the Gaussian with the exponential tail numerically (stable for any tau), then
        # average groups of `fine` samples back to the requested spacing.
        fine = 8
        step = 1.0 / (oversample * fine)
        before = int(math.ceil(5 * s * oversample)) + 1
        after = int(math.ceil((5 * s + 12 * tau) * oversample)) + 1
        t = np.arange(-before * fine, (after + 1) * fine) * step - 0.5 / oversample + 0.5 * step
        g = np.exp(-0.5 * (t / s) ** 2)
        if tau >= 1e-3:
            # Trapezoidal weights (half weight at zero delay): a left-point sum would put the pulse early by step/2.
            tail = np.exp(-np.arange(0, int(math.ceil(12 * tau / step)) + 1) * step / tau)
            tail[0] *= 0.5
            g = _convolve(g, tail)[: t.size]
        k = g.reshape(-1, fine).mean(axis=1)
        return k / k.sum(), before


DIRECT_CONVOLVE_MAX = 10_000_000
"""Products of the two lengths up to which `_convolve` sums directly (exact); beyond it, by FFT."""


def _convolve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The full discrete convolution of `a` and `b`: directly while that is cheap, else through the FFT (a long
    exponential tail, tau of hundreds of bins, made the direct sum take minutes), its rounding noise clipped at 0."""
    if a.size * b.size <= DIRECT_CONVOLVE_MAX:
        return np.convolve(a, b)
    n = a.size + b.size - 1
    size = 1 << (n - 1).bit_length()
    return np.maximum(np.fft.irfft(np.fft.rfft(a, size) * np.fft.rfft(b, size), size)[:n], 0.0)


@dataclass(frozen=True)
class SensorModel:
    """What a histogram means: geometry of the zones, the time axis, the pulse and the photon statistics.

    Rates are photons per bin per laser cycle; a histogram holds counts over `cycles` laser cycles.
    """

    name: str
    """Preset name this model came from (or 'custom')."""
    n_bins: int
    """Bins per histogram."""
    bin_width_m: float
    """One-way distance covered by one bin (metres)."""
    zero_bin: float
    """Bin coordinate of a return at zero range (where the pulse's arrival time sits for r = 0)."""
    zones: tuple[Zone, ...]
    """One entry per histogram channel, in the sensor's channel order."""
    pulse: Pulse
    """Laser impulse response."""
    signal_scale: float
    """Photons per cycle per unit albedo per unit of the integral of cos(incidence) / r^2 dOmega (sr / m^2)."""
    background: float
    """Ambient background (photons per bin per cycle), flat in time."""
    cycles: int
    """Laser cycles summed in one histogram."""
    pileup: bool = True
    """The detector stops at its first photon per cycle (Coates pile-up)."""
    crosstalk: float = 0.0
    """Each zone also receives this fraction of the sum of all zones' signal (multi-zone sensors)."""
    jitter_bins: float = 0.0
    """Gaussian timing jitter (sigma, bins) applied to detection probabilities."""
    max_count: int = 2**32 - 1
    """Largest count a bin can hold (24-bit counters on the TMF8820)."""
    ignore_bins: tuple[int, ...] = ()
    """Bins whose counts are unreliable (e.g. the TMF8820's bin 0) and are left out of fits."""
    has_reference: bool = False
    """Captures carry a reference histogram (the laser pulse through an internal path) per frame."""
    notes: str = ""
    """Where the numbers come from."""

    @property
    def n_zones(self) -> int:
        return len(self.zones)

    def bin_of_range(self, r_m):
        """Bin coordinate of the arrival of a return from one-way range r (metres): a number, a numpy array or a torch
        tensor, and the coordinate comes back as the same kind (so that the fit's torch code reads the one formula)."""
        return self.zero_bin + r_m / self.bin_width_m

    def range_of_bin(self, t):
        """One-way range (metres) of a return that arrives at bin coordinate t (a number, numpy array or tensor)."""
        return (t - self.zero_bin) * self.bin_width_m

    @property
    def max_range_m(self) -> float:
        return float(self.range_of_bin(self.n_bins))

    def validate(self) -> "SensorModel":
        """Check every field; returns self. Wrong types (a string for a number, ...) are SensorModelErrors too."""
        try:
            return self._validate()
        except (TypeError, ValueError) as exc:
            raise SensorModelError(f"sensor model {self.name!r}: a field has the wrong type ({exc})") from None

    def _validate(self) -> "SensorModel":
        where = f"sensor model {self.name!r}"
        _check_types(self, _MODEL_TYPES, where)
        if not all(isinstance(z, Zone) for z in self.zones) or not isinstance(self.pulse, Pulse):
            raise SensorModelError(f"{where}: zones must be Zone records and pulse a Pulse record")
        if not 4 <= self.n_bins <= 65536:
            raise SensorModelError(f"{where}: n_bins {self.n_bins} must be an integer in [4, 65536]")
        if not (math.isfinite(self.bin_width_m) and 1e-6 <= self.bin_width_m <= 1.0):
            raise SensorModelError(f"{where}: bin width {self.bin_width_m} m is outside [1e-6, 1] m")
        if not (math.isfinite(self.zero_bin) and -self.n_bins <= self.zero_bin < self.n_bins):
            raise SensorModelError(f"{where}: zero bin {self.zero_bin} is outside the histogram")
        if not self.zones:
            raise SensorModelError(f"{where}: needs at least one zone")
        for i, z in enumerate(self.zones):
            z.validate(f"{where} zone {i}")
        self.pulse.validate(f"{where} pulse")
        for key, lo, hi in (("signal_scale", 0.0, MAX_SIGNAL_SCALE), ("background", 0.0, 1.0),
                            ("crosstalk", 0.0, 1.0), ("jitter_bins", 0.0, 1000.0)):
            v = getattr(self, key)
            if not (math.isfinite(v) and lo <= v <= hi):
                raise SensorModelError(f"{where}: {key} = {v} is outside [{lo}, {hi}]")
        if not 1 <= self.cycles <= 10**10:
            raise SensorModelError(f"{where}: cycles {self.cycles} must be an integer in [1, 1e10]")
        if not 1 <= self.max_count <= 2**32 - 1:
            raise SensorModelError(f"{where}: max_count {self.max_count} must fit in uint32")
        if any(not 0 <= b < self.n_bins for b in self.ignore_bins):
            raise SensorModelError(f"{where}: ignore_bins {self.ignore_bins} must lie in 0..{self.n_bins - 1}")
        return self

    def with_(self, **changes) -> "SensorModel":
        """A copy with some fields changed, validated."""
        return replace(self, **changes).validate()

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "SensorModel":
        """Build and validate a model from its JSON form; unknown or missing keys are one-line errors."""
        if not isinstance(data, dict):
            raise SensorModelError(f"sensor model must be a JSON object, got {type(data).__name__}")
        data = dict(data)
        try:
            zones, pulse = data.pop("zones"), data.pop("pulse")
        except KeyError as exc:
            raise SensorModelError(f"sensor model lacks {exc.args[0]!r}") from None
        if not isinstance(zones, (list, tuple)):
            raise SensorModelError(f"sensor model: zones must be a list of zone objects, got {type(zones).__name__}")
        zones = tuple(_dataclass_from(Zone, z, "zone") for z in zones)
        pulse = _dataclass_from(Pulse, pulse, "pulse")
        model = _dataclass_from(cls, {**data, "zones": zones, "pulse": pulse}, "sensor model")
        return model.validate()


_MODEL_TYPES = {"name": "string", "n_bins": "integer", "bin_width_m": "number", "zero_bin": "number",
                "zones": "list", "signal_scale": "number", "background": "number", "cycles": "integer",
                "pileup": "true or false", "crosstalk": "number", "jitter_bins": "number", "max_count": "integer",
                "ignore_bins": "integers", "has_reference": "true or false", "notes": "string"}
"""The JSON type of each of SensorModel's plain fields (docs/capture_format.md)."""


def _is_integer(v) -> bool:
    """A Python int (what JSON gives, and what JSON can write back) but not a bool: JSON's true is no count, though
    Python counts it as 1."""
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    """A real number, numpy's too, but not a bool."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


_TYPE_TESTS = {
    "string": (lambda v: isinstance(v, str), "a string"),
    "integer": (_is_integer, "an integer"),
    "number": (_is_number, "a number"),
    # Only a JSON boolean: the string "false" is truthy, and it turned pile-up on.
    "true or false": (lambda v: isinstance(v, bool), "true or false"),
    "list": (lambda v: isinstance(v, (tuple, list)), "a list"),
    # Indices (bins, a table's origin) must be whole: 0.5 passed the range checks and crashed the fit later.
    "integers": (lambda v: isinstance(v, (tuple, list)) and all(_is_integer(x) for x in v), "a list of integers"),
    "numbers": (lambda v: isinstance(v, (tuple, list)) and all(_is_number(x) for x in v), "a list of numbers"),
}
"""Kind -> (test, what the error says a value must be)."""


def _check_types(record, kinds: dict, where: str) -> None:
    """One-line SensorModelError naming the first field of `record` whose value is not of its kind in `kinds`
    (field name -> a key of _TYPE_TESTS)."""
    for key, kind in kinds.items():
        value = getattr(record, key)
        test, what = _TYPE_TESTS[kind]
        if not test(value):
            shown = repr(list(value) if isinstance(value, tuple) else value)
            shown = shown if len(shown) <= 40 else shown[:37] + "..."
            raise SensorModelError(f"{where}: {key} = {shown} must be {what}")


def _dataclass_from(cls, data, what: str):
    if not isinstance(data, dict):
        raise SensorModelError(f"{what} must be a JSON object, got {type(data).__name__}")
    names = {f.name: f for f in fields(cls)}
    unknown = set(data) - set(names)
    if unknown:
        raise SensorModelError(f"{what} has unknown keys {sorted(unknown)}")
    # Said as the manifest's key, not as the constructor's signature ("missing 1 required positional argument").
    missing = [name for name, f in names.items()
               if name not in data and f.default is MISSING and f.default_factory is MISSING]
    if missing:
        raise SensorModelError(f"{what} lacks {', '.join(map(repr, missing))}")
    kwargs = {}
    for key, value in data.items():
        if isinstance(value, list):
            value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
        kwargs[key] = value
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise SensorModelError(f"{what}: {exc}") from None
