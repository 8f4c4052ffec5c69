"""What the sweep's imaging parameters do to the simulated histograms: bins change but the range and the pulse's
width in time stay; a wider field spreads the same laser power; ambient light is a flux in time."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from spadscan.protocol.errors import ConfigError
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, Simulator
from spadscan.sweep.params import (bin_ps_of, check_value, fov_deg_of, point_ambient, with_bin_ps,
                                   with_fov_deg)

BASE_PS = bin_ps_of(sensor_preset("lcspc-sim"))


def plate(distance_m: float, half_width_m: float):
    """A square plate facing a sensor at the origin that looks along +z."""
    mesh = trimesh.creation.box([2 * half_width_m, 2 * half_width_m, 0.002])
    mesh.apply_translation([0, 0, distance_m + 0.001])
    return mesh


def signal(mesh, sensor) -> np.ndarray:
    """Expected signal photons per bin per cycle of one view from the origin (no noise)."""
    return Simulator(mesh, sensor, SimSettings(rays_per_zone=20000), seed=0).signal_rates(np.eye(4)[None])[0, 0]


@pytest.mark.parametrize("factor", [2.0, 8.0, 32.0])
def test_wider_bins_keep_the_range_the_return_and_its_photons(factor):
    base = sensor_preset("lcspc-sim")
    wide = with_bin_ps(base, BASE_PS * factor)
    assert bin_ps_of(wide) == pytest.approx(BASE_PS * factor)
    assert wide.max_range_m == pytest.approx(base.max_range_m, abs=wide.bin_width_m)
    assert wide.range_of_bin(0.0) == pytest.approx(base.range_of_bin(0.0))  # zero range stays put, in metres
    sigma_m = wide.pulse.sigma_bins * wide.bin_width_m
    assert sigma_m == pytest.approx(max(base.pulse.sigma_bins * base.bin_width_m, 0.05 * wide.bin_width_m))
    target = plate(0.3, 0.02)
    h_base, h_wide = signal(target, base), signal(target, wide)
    assert h_wide.sum() == pytest.approx(h_base.sum(), rel=0.01)  # the same photons, in fewer bins
    # The return's centre of mass lies at the plate's range (plus the pulse's tail) in both.
    def centre_m(h, s):
        return float(s.range_of_bin((np.arange(s.n_bins) + 0.5) @ h / h.sum()))
    assert centre_m(h_wide, wide) == pytest.approx(centre_m(h_base, base), abs=0.3 * wide.bin_width_m + 5e-4)


def test_a_wider_field_spreads_the_same_laser_power():
    base = sensor_preset("lcspc-sim")
    assert fov_deg_of(base) == pytest.approx(30.06)
    wide = with_fov_deg(base, 60.0)
    assert math.degrees(wide.zones[0].half_angle_rad) == pytest.approx(30.0)
    small = plate(0.3, 0.01)  # inside both fields: it gets the power per steradian
    ratio = signal(small, wide).sum() / signal(small, base).sum()
    solid = wide.zones[0].solid_angle_sr() / base.zones[0].solid_angle_sr()
    assert ratio == pytest.approx(1 / solid, rel=0.03)
    # A wall that fills both fields returns the same power but for the fall-off off axis: per unit of power the
    # return is the mean of cos(incidence) / r^2 = cos^3 / d^2 over the cone, (1 - cos^4 a) / (4 (1 - cos a)).
    def mean_cos3(half_angle):
        return (1 - math.cos(half_angle) ** 4) / (4 * (1 - math.cos(half_angle)))
    wall = plate(0.3, 2.0)
    expected = mean_cos3(wide.zones[0].half_angle_rad) / mean_cos3(base.zones[0].half_angle_rad)
    assert signal(wall, wide).sum() / signal(wall, base).sum() == pytest.approx(expected, rel=0.01)


def test_rectangular_zones_scale_together():
    tmf = sensor_preset("tmf8820")
    wider = with_fov_deg(tmf, 2 * fov_deg_of(tmf))
    assert fov_deg_of(wider) == pytest.approx(2 * fov_deg_of(tmf))
    assert sum(z.solid_angle_sr() for z in wider.zones) * wider.signal_scale == pytest.approx(
        sum(z.solid_angle_sr() for z in tmf.zones) * tmf.signal_scale)


def test_ambient_is_a_flux_in_time():
    params = {"ambient": 2e-4, "bin_ps": 4 * BASE_PS}
    assert point_ambient(params, BASE_PS) == pytest.approx(8e-4)


@pytest.mark.parametrize("name, value, message", [
    ("views", 2.5, "must be a whole number"), ("power", float("nan"), "finite"), ("seed", -1, "out of range"),
    ("fov_deg", 0, "must be > 0"), ("target_m", [0, 0], "three finite numbers"), ("cycles", 10**11, "out of range"),
])
def test_values_are_checked(name, value, message):
    with pytest.raises(ConfigError, match=message):
        check_value(name, value, "here")


def test_whole_floats_are_counts():
    assert check_value("views", 64.0, "here") == 64 and isinstance(check_value("views", 64.0, "here"), int)
