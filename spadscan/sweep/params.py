"""The imaging parameters a sweep varies, their units and checks, and what they do to the simulation.

Units at this edge are the user's: degrees, picoseconds, metres; inside, the sensor model's metres and radians.

- `bin_ps`: the width of a histogram bin in time (picoseconds; one bin covers bin_ps x c / 2 metres of one-way
  range). The histogram keeps the preset's range (more, narrower bins or fewer, wider ones), and the laser pulse keeps
  its width in time, so its width in bins follows the bins.
- `fov_deg`: the full field of view in degrees: a cone's apex angle (twice the half-angle), or for rectangular zones
  the whole field across x, every zone scaled alike. The laser's power is spread over the field, so the signal per
  steradian falls as the field's solid angle grows (the same laser behind a wider diffuser).
- `ambient`: background photons per bin per laser cycle *at the base condition's bin size*; a point with wider bins
  collects proportionally more per bin (the ambient flux in time is the scene's, not the sensor's).
- `power`: the laser's power relative to the sensor preset's (unitless: it absorbs quantum efficiency);
  `cycles`: laser cycles summed in one histogram; `views`, `min_elevation_deg`, ...: the schedule of poses.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from spadscan.protocol import schedules
from spadscan.protocol.errors import ConfigError, SpadscanError
from spadscan.protocol.sensor_model import MAX_RECT_TAN
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings

C_M_PER_S = 299_792_458.0
"""Speed of light: a bin of t seconds covers c t / 2 metres of one-way range."""
MIN_PULSE_SIGMA_BINS = 0.05
"""The sensor model's narrowest pulse (bins): bins much wider than the pulse see it as a spike."""
SCHEDULES = ("fibonacci", "rings")
RINGS_ELEVATIONS = dict(zip(("min_elevation_deg", "max_elevation_deg"), schedules.RINGS_BAND_DEG))
"""The rings schedule's own band (schedules.RINGS_BAND_DEG), as the keys of a point."""


@dataclass(frozen=True)
class Param:
    """One parameter of the base condition: its type, limits, unit and what it means."""

    name: str
    kind: str
    """'int', 'float', 'str' or 'vec3'."""
    unit: str
    help: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    """True: the value must exceed `lo` (not merely reach it)."""
    axis: bool = True
    """Whether a grid may vary it."""
    log: bool = False
    """Whether a plot spreads its values on a log axis."""
    label: str = ""
    """Axis label of its panel in Figure A."""


PARAMS: dict[str, Param] = {p.name: p for p in (
    Param("sensor", "str", "", "sensor model preset (lcspc-sim, tmf8820)", axis=False),
    Param("schedule", "str", "", "fibonacci: equal-area spiral; rings: elevation rings", axis=False),
    Param("views", "int", "", "number of views", 1, 100_000, log=True, label="number of views"),
    Param("rings", "int", "", "elevation rings (schedule rings only)", 1, 10_000, label="elevation rings"),
    Param("min_elevation_deg", "float", "deg", "lowest view elevation", -89.0, 89.0,
          label="minimum elevation (deg)"),
    Param("max_elevation_deg", "float", "deg", "highest view elevation", -89.0, 90.0,
          label="maximum elevation (deg)"),
    Param("radius_m", "float", "m", "distance from the sensor to the target", 0.0, 100.0, lo_open=True,
          label="distance to the target (m)"),
    Param("target_m", "vec3", "m", "the point every view looks at", axis=False),
    Param("bin_ps", "float", "ps", "bin size in time (temporal resolution)", 0.1, 100_000.0, log=True,
          label="bin size (ps)"),
    Param("fov_deg", "float", "deg", "full field of view", 0.0, 170.0, lo_open=True, log=True,
          label="full field of view (deg)"),
    Param("power", "float", "", "laser power relative to the sensor preset", 0.0, 1e9, lo_open=True, log=True,
          label="illumination power (relative)"),
    Param("ambient", "float", "photons/bin/cycle", "ambient background per bin per cycle at the base bin size",
          0.0, 1.0, log=True, label="ambient (photons / bin / cycle)"),
    Param("cycles", "int", "", "laser cycles per histogram", 1, 10**10, log=True, label="laser cycles"),
    Param("albedo", "float", "", "Lambertian albedo of the object", 0.0, 1e3, lo_open=True, log=True,
          label="albedo"),
    Param("rays_per_zone", "int", "", "rays the simulator casts per zone per view", 1, 10_000_000, log=True,
          label="simulator rays per zone"),
    Param("seed", "int", "", "random seed of the photon draws and of the reconstruction", 0, 2**63 - 1,
          label="seed"),
)}


def check_value(name: str, value, where: str):
    """`value` checked against parameter `name` and normalised (ints stay ints, floats become floats); a one-line
    ConfigError otherwise."""
    p = PARAMS[name]
    if p.kind == "str":
        if not isinstance(value, str):
            raise ConfigError(f"{where}: {name} = {value!r} must be a string")
        return value
    if p.kind == "vec3":
        if not (isinstance(value, list) and len(value) == 3 and all(_is_number(v) for v in value)
                and all(math.isfinite(v) for v in value)):
            raise ConfigError(f"{where}: {name} = {value!r} must be three finite numbers (metres)")
        return [float(v) for v in value]
    if p.kind == "int":
        ok = isinstance(value, int) and not isinstance(value, bool)
        if not ok and isinstance(value, float) and value.is_integer():
            value, ok = int(value), True
        if not ok:
            raise ConfigError(f"{where}: {name} = {value!r} must be a whole number")
    elif not (_is_number(value) and math.isfinite(value)):
        raise ConfigError(f"{where}: {name} = {value!r} must be a finite number" + (f" ({p.unit})" if p.unit else ""))
    else:
        value = float(value)
    too_low = p.lo is not None and (value <= p.lo if p.lo_open else value < p.lo)
    if too_low or (p.hi is not None and value > p.hi):
        bound = shown if p.kind == "int" else (lambda v: f"{v:g}")
        low = f"> {bound(p.lo)}" if p.lo_open else f">= {bound(p.lo)}"
        unit = f" {p.unit}" if p.unit else ""
        raise ConfigError(f"{where}: {name} = {shown(value)}{unit} is out of range (must be {low} and <= "
                          f"{bound(p.hi)})")
    return value


def shown(value) -> str:
    """A parameter's value for messages: whole numbers with every digit (a seed of 2^63 - 1 read as 9.22337e+18
    names another number), other numbers short (:g), anything else as itself."""
    if isinstance(value, int) and not isinstance(value, bool):
        return str(value)
    return f"{value:g}" if isinstance(value, float) else str(value)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def bin_ps_of(sensor) -> float:
    """A sensor model's bin size in picoseconds."""
    return 2.0 * sensor.bin_width_m / C_M_PER_S * 1e12


def fov_deg_of(sensor) -> float:
    """A sensor model's full field of view in degrees: the cone's apex angle, or the rect zones' extent across x."""
    zones = sensor.zones
    if all(z.kind == "cone" for z in zones) and len(zones) == 1:
        return 2.0 * math.degrees(zones[0].half_angle_rad)
    if all(z.kind == "rect" for z in zones):
        lo = min(z.tan_x[0] for z in zones)
        hi = max(z.tan_x[1] for z in zones)
        return math.degrees(math.atan(hi) - math.atan(lo))
    raise ConfigError(f"sensor {sensor.name!r}: its field of view is neither one cone nor rectangular zones; "
                      f"fov_deg cannot change it")


def defaults_for(sensor) -> dict:
    """The base condition's defaults: LCSPCData's schedule and the sensor preset's own bins, field and photons."""
    return {"schedule": "fibonacci", "views": 256, "rings": None, "min_elevation_deg": 0.0,
            "max_elevation_deg": 90.0, "radius_m": 0.5, "target_m": [0.0, 0.0, 0.0],
            "bin_ps": bin_ps_of(sensor), "fov_deg": fov_deg_of(sensor), "power": 1.0, "ambient": None,
            "cycles": int(sensor.cycles), "albedo": 1.0, "rays_per_zone": None, "seed": 0}


def with_bin_ps(sensor, bin_ps: float):
    """The sensor with bins of `bin_ps` picoseconds over the same range; the pulse keeps its width in time."""
    old = bin_ps_of(sensor)
    if math.isclose(bin_ps, old, rel_tol=1e-9):
        return sensor
    if sensor.pulse.kind != "exgauss":
        raise ConfigError(f"bin_ps: sensor {sensor.name!r} has a measured (tabulated) pulse, which cannot be "
                          f"resampled to other bins; vary bin_ps with a parametric-pulse sensor such as lcspc-sim")
    if sensor.ignore_bins:
        raise ConfigError(f"bin_ps: sensor {sensor.name!r} ignores bins {list(sensor.ignore_bins)}, which mean "
                          f"nothing at another bin size")
    ratio = old / bin_ps  # new bins per old bin
    pulse = replace(sensor.pulse, sigma_bins=max(MIN_PULSE_SIGMA_BINS, sensor.pulse.sigma_bins * ratio),
                    tau_bins=sensor.pulse.tau_bins * ratio)
    n_bins = max(4, int(math.ceil(sensor.n_bins * ratio - 1e-9)))
    return sensor.with_(bin_width_m=bin_ps * 1e-12 * C_M_PER_S / 2.0, n_bins=n_bins,
                        zero_bin=sensor.zero_bin * ratio, pulse=pulse, jitter_bins=sensor.jitter_bins * ratio)


def with_fov_deg(sensor, fov_deg: float):
    """The sensor with a full field of view of `fov_deg` degrees, its laser power spread over the new field."""
    old = fov_deg_of(sensor)
    if math.isclose(fov_deg, old, rel_tol=1e-9):
        return sensor
    if sensor.zones[0].kind == "cone":
        if not fov_deg < 180.0:
            raise ConfigError(f"fov_deg = {fov_deg:g}: a cone's full angle must be under 180 degrees")
        zones = (replace(sensor.zones[0], half_angle_rad=math.radians(fov_deg / 2.0)),)
    else:
        k = math.tan(math.radians(fov_deg / 2.0)) / math.tan(math.radians(old / 2.0))
        widest = max(abs(t) for z in sensor.zones for t in (*z.tan_x, *z.tan_y))
        if not k * widest < MAX_RECT_TAN:
            limit = 2.0 * math.degrees(math.atan(MAX_RECT_TAN / widest * math.tan(math.radians(old / 2.0))))
            # Without a value: the caller's prefix names the entry ("[grid] fov_deg = 170").
            raise ConfigError(f"fov_deg: sensor {sensor.name!r} has rectangular zones, whose field widens only to "
                              f"under {math.floor(limit * 10) / 10:g} deg (zone edges within |tan| < "
                              f"{MAX_RECT_TAN:g})")
        zones = tuple(replace(z, tan_x=(z.tan_x[0] * k, z.tan_x[1] * k), tan_y=(z.tan_y[0] * k, z.tan_y[1] * k))
                      for z in sensor.zones)
    solid_old = sum(z.solid_angle_sr() for z in sensor.zones)
    solid_new = sum(z.solid_angle_sr() for z in zones)
    return sensor.with_(zones=zones, signal_scale=sensor.signal_scale * solid_old / solid_new)


def point_sensor(params: dict):
    """The sensor model of a point (before the photon settings, which the simulator folds in)."""
    sensor = sensor_preset(params["sensor"])
    return with_fov_deg(with_bin_ps(sensor, params["bin_ps"]), params["fov_deg"])


def point_ambient(params: dict, base_bin_ps: float) -> float:
    """Background photons per bin per cycle of a point: the base condition's rate scaled to its bins."""
    return params["ambient"] * params["bin_ps"] / base_bin_ps


def point_settings(params: dict, base_bin_ps: float):
    """The simulator's photon settings (protocol.simulator.SimSettings) of a point, checked."""
    extra = {} if params["rays_per_zone"] is None else {"rays_per_zone": params["rays_per_zone"]}
    return SimSettings(power=params["power"], ambient=point_ambient(params, base_bin_ps), cycles=params["cycles"],
                       albedo=params["albedo"], **extra).check()


def point_poses(params: dict) -> tuple[np.ndarray, dict]:
    """(poses (n, 4, 4), the schedule record a capture stores) of a point."""
    common = dict(radius_m=params["radius_m"], target=tuple(params["target_m"]),
                  min_elevation_deg=params["min_elevation_deg"], max_elevation_deg=params["max_elevation_deg"])
    record = {"kind": params["schedule"], "views": params["views"], "radius_m": params["radius_m"],
              "target_m": list(params["target_m"]), "min_elevation_deg": params["min_elevation_deg"],
              "max_elevation_deg": params["max_elevation_deg"], "seed": params["seed"]}
    if params["schedule"] == "fibonacci":
        return schedules.fibonacci_hemisphere(params["views"], **common), record
    rings = params["rings"]
    if params["views"] % rings:
        raise ConfigError(f"views = {params['views']} is not a multiple of rings = {rings}")
    record.update(rings=rings, per_ring=params["views"] // rings)
    return schedules.elevation_rings(rings, params["views"] // rings, **common), record


def check_point(params: dict, base_bin_ps: float) -> dict:
    """Build everything a point's simulation needs once, so that a bad combination is a one-line error before the
    sweep starts. Returns the point's sensor model and photon settings as dicts (part of what its id is made from:
    the settings hold what `params` alone does not say, such as the ambient rate at the point's bins)."""
    if params["schedule"] not in SCHEDULES:
        raise ConfigError(f"schedule = {params['schedule']!r} is not one of {', '.join(SCHEDULES)}")
    if params["schedule"] == "fibonacci" and params["rings"] is not None:
        raise ConfigError("rings is for schedule = 'rings' (the fibonacci spiral has none)")
    if not params["min_elevation_deg"] < params["max_elevation_deg"]:
        raise ConfigError(f"min_elevation_deg = {params['min_elevation_deg']:g} must be below max_elevation_deg = "
                          f"{params['max_elevation_deg']:g}")
    if (params["schedule"] == "rings" and params["max_elevation_deg"] >= 90.0 and params["rings"] > 1
            and params["views"] // params["rings"] > 1):
        raise ConfigError(f"max_elevation_deg = {params['max_elevation_deg']:g} puts the top ring of schedule "
                          f"'rings' at the zenith, where its {params['views'] // params['rings']} views are one "
                          f"viewpoint; keep it below 90 (default {RINGS_ELEVATIONS['max_elevation_deg']:g})")
    try:
        sensor = point_sensor(params)
        settings = point_settings(params, base_bin_ps)
        point_poses(params)
    except ConfigError:
        raise
    except SpadscanError as exc:
        raise ConfigError(str(exc)) from None
    return {"sensor": sensor.to_dict(), "settings": asdict(settings)}


__all__ = ["PARAMS", "Param", "check_value", "shown", "defaults_for", "bin_ps_of", "fov_deg_of", "with_bin_ps",
           "with_fov_deg", "point_sensor", "point_settings", "point_poses", "point_ambient", "check_point",
           "C_M_PER_S", "SCHEDULES", "RINGS_ELEVATIONS"]
