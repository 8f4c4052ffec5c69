"""Sensor model presets: `tmf8820` (the real ams sensor) and `lcspc-sim` (the LCSPCData simulator).

Numbers come from SENSOR_FACTS (fits of a ray-cast forward model to the public dataset) and are re-fitted by
`tools/fit_sensor.py`; each preset's `notes` field says where its values come from.
"""

from __future__ import annotations

import math

from .errors import SensorModelError
from .sensor_model import Pulse, SensorModel, Zone

# TMF8820 zone edges in the sensor frame (tan of the angle), channel 1..9 -> column (i-1)//3, row (i-1)%3.
_TMF_TAN_X = (0.294, 0.084, -0.084, -0.294)  # column 0 looks toward +x
_TMF_TAN_Y = (0.291, 0.097, -0.097, -0.291)  # row 0 looks toward +y
# Per-zone gains relative to the centre channel 5 (emitter pattern; calibrate per sensor).
_TMF_GAINS = (0.31, 0.48, 0.50, 0.63, 1.0, 1.16, 0.37, 0.57, 0.62)


def _tmf8820_zones() -> tuple[Zone, ...]:
    zones = []
    for i in range(9):
        c, r = i // 3, i % 3
        zones.append(Zone(kind="rect",
                          tan_x=(_TMF_TAN_X[c + 1], _TMF_TAN_X[c]),
                          tan_y=(_TMF_TAN_Y[r + 1], _TMF_TAN_Y[r]),
                          gain=_TMF_GAINS[i]))
    return tuple(zones)


def tmf8820() -> SensorModel:
    """ams TMF8820 in short-range high-accuracy mode, 3x3 zones on SPAD map 1, full histograms."""
    return SensorModel(
        name="tmf8820",
        n_bins=128,
        bin_width_m=1 / 73.48,
        zero_bin=13.25,
        zones=_tmf8820_zones(),
        pulse=Pulse(kind="exgauss", sigma_bins=0.9, tau_bins=1.6),
        signal_scale=0.095,
        background=3.0e-5,
        cycles=4_000_000,
        pileup=True,
        crosstalk=0.021,
        jitter_bins=0.0,
        max_count=2**24 - 1,
        ignore_bins=(0,),
        has_reference=True,
        notes=("Time axis 73.48 bins/m, zero range at bin 13.25 (ams); zones, gains, crosstalk 0.021, signal 0.08-0.11 "
               "photons/cycle per unit albedo x int cos/r^2 dOmega, ~4 M cycles per frame and background 60-190 "
               "counts/bin from a fit to LCSPCData's real pyramid (SENSOR_FACTS). Captures carry the reference "
               "histogram; its pulse replaces this exgauss stand-in where available."),
    ).validate()


def lcspc_sim() -> SensorModel:
    """The simulator behind LCSPCData's simulated scenes: one 30-degree cone, 1024 bins of 1.25 mm."""
    return SensorModel(
        name="lcspc-sim",
        n_bins=1024,
        bin_width_m=1 / 800.0,
        zero_bin=-1.1,
        zones=(Zone(kind="cone", half_angle_rad=math.radians(15.25)),),
        pulse=Pulse(kind="exgauss", sigma_bins=2.0, tau_bins=3.6),
        signal_scale=1.1,
        background=2.48e-4,
        cycles=5000,
        pileup=True,
        crosstalk=0.0,
        jitter_bins=0.0,
        max_count=2**32 - 1,
        notes="SENSOR_FACTS values (800 bins/m, peak at 800 d + 0.9, sigma 2.0, tau 3.6, half-angle 15.25 deg).",
    ).validate()


PRESETS = {"tmf8820": tmf8820, "lcspc-sim": lcspc_sim}


def sensor_preset(name: str) -> SensorModel:
    """The preset called `name`; a one-line error lists the known names."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise SensorModelError(f"unknown sensor preset {name!r} (known: {', '.join(PRESETS)})") from None
