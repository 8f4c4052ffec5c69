"""The sensor model record: JSON round trip, validation with one-line errors, zone geometry, pulse kernels."""

import json
import math

import numpy as np
import pytest

from spadscan.protocol.errors import SensorModelError
from spadscan.protocol.sensor_model import Pulse, SensorModel, Zone, in_any_zone, zone_masks
from spadscan.protocol.sensor_presets import PRESETS, sensor_preset
from spadscan.protocol.transient import FineAxis, convolve_pulse


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_round_trip_through_json(name):
    model = sensor_preset(name)
    again = SensorModel.from_dict(json.loads(json.dumps(model.to_dict())))
    assert again == model
    assert again.n_zones == len(model.zones) and again.name == name


def test_presets_describe_their_sensors():
    tmf, sim = sensor_preset("tmf8820"), sensor_preset("lcspc-sim")
    assert (tmf.n_zones, tmf.n_bins, tmf.has_reference) == (9, 128, True)
    assert tmf.bin_width_m == pytest.approx(1 / 73.48, rel=0.05) and tmf.max_count == 2**24 - 1
    assert (sim.n_zones, sim.n_bins, sim.cycles) == (1, 1024, 5000)
    assert 1 / sim.bin_width_m == pytest.approx(800, abs=3)
    # a surface at 0.4 m arrives near bin 13.25 + 73.48 * 0.4 on the TMF8820 and near 800 * 0.4 on lcspc-sim
    assert tmf.bin_of_range(0.4) == pytest.approx(13.25 + 73.48 * 0.4, abs=1.0)
    assert sim.bin_of_range(0.4) == pytest.approx(320, abs=3)
    assert sim.range_of_bin(sim.bin_of_range(0.4)) == pytest.approx(0.4)
    with pytest.raises(SensorModelError, match="known: tmf8820, lcspc-sim"):
        sensor_preset("nope")


def test_tmf8820_zone_layout_follows_the_channel_order():
    zones = sensor_preset("tmf8820").zones
    centre = [(np.mean(z.tan_x), np.mean(z.tan_y)) for z in zones]
    assert centre[0][0] > 0 and centre[0][1] > 0  # channel 1 looks toward (+x, +y)
    assert centre[2][0] > 0 and centre[2][1] < 0  # channel 3 toward (+x, -y)
    assert centre[8][0] < 0 and centre[8][1] < 0  # channel 9 toward (-x, -y)
    assert centre[4] == pytest.approx((0, 0))
    assert zones[4].gain == 1.0


def test_a_zone_holds_what_lies_in_its_field_of_view_for_arrays_and_tensors_alike():
    torch = pytest.importorskip("torch")
    cone = Zone(kind="cone", half_angle_rad=math.radians(10), axis=(0.0, 0.0, 1.0))
    rect = Zone(kind="rect", tan_x=(-0.1, 0.2), tan_y=(0.0, 0.3))
    pts = np.array([[0, 0, 1.0],          # on the boresight
                    [0.17, 0, 1.0],       # 9.6 deg off: in the cone
                    [0.18, 0, 1.0],       # 10.2 deg off: out of the cone
                    [0, 0, -1.0],         # behind the sensor
                    [0.05, 0.29, 1.0],    # in the rect
                    [0.05, 0.31, 1.0],    # above the rect
                    [0, 0, 0.0]])         # the sensor itself
    assert cone.holds(pts).tolist() == [True, True, False, False, False, False, False]
    assert rect.holds(pts).tolist() == [True, True, True, False, True, False, False]  # y = 0: on its edge, held
    rng = np.random.default_rng(0)
    many = rng.normal(size=(5000, 3))
    for zone in (*sensor_preset("tmf8820").zones, *sensor_preset("lcspc-sim").zones):
        on_array = zone.holds(many)
        assert isinstance(on_array, np.ndarray) and on_array.any() and not on_array.all()
        assert zone.holds(torch.as_tensor(many)).numpy().tolist() == on_array.tolist()
        assert zone.holds(3.0 * many).tolist() == on_array.tolist(), "a direction, whatever its length"


def test_a_point_in_any_zone_is_in_the_sensors_view_for_arrays_and_tensors_alike():
    torch = pytest.importorskip("torch")
    zones = sensor_preset("tmf8820").zones
    many = np.random.default_rng(1).normal(size=(5000, 3))
    union = np.zeros(len(many), bool)
    for zone in zones:
        union |= zone.holds(many)
    assert union.any() and not union.all()
    assert in_any_zone(zones, many).tolist() == union.tolist()
    assert in_any_zone(zones, torch.as_tensor(many)).numpy().tolist() == union.tolist()
    assert in_any_zone(zones[:1], many).tolist() == zones[0].holds(many).tolist()


def test_solid_angles():
    cone = Zone(kind="cone", half_angle_rad=math.radians(15))
    assert cone.solid_angle_sr() == pytest.approx(2 * math.pi * (1 - math.cos(math.radians(15))))
    rect = Zone(kind="rect", tan_x=(-0.1, 0.3), tan_y=(0.05, 0.2))
    x = np.linspace(-0.1, 0.3, 2001)
    y = np.linspace(0.05, 0.2, 2001)
    xx, yy = np.meshgrid((x[1:] + x[:-1]) / 2, (y[1:] + y[:-1]) / 2)
    quad = (np.diff(x)[0] * np.diff(y)[0] / (1 + xx**2 + yy**2) ** 1.5).sum()
    assert rect.solid_angle_sr() == pytest.approx(quad, rel=1e-6)


@pytest.mark.parametrize("half_angle", [1e-9, 1e-12, 1e-100])
def test_a_very_narrow_cone_keeps_its_solid_angle(half_angle):
    """pi a^2 for a small half-angle a: 2 pi (1 - cos a) underflows to 0 below about 1e-8 rad, and a zone of no solid
    angle weighed its rays 0 / 0 (a NaN in the fit's set-up)."""
    cone = Zone(kind="cone", half_angle_rad=half_angle)
    assert cone.solid_angle_sr() == pytest.approx(math.pi * half_angle ** 2, rel=1e-9)


@pytest.mark.parametrize("sigma,tau,over", [(2.0, 3.6, 1), (2.0, 3.6, 8), (0.9, 0.0, 4), (0.5, 1.5, 8),
                                             (1.0, 300.0, 8)])  # a long tail: summed by FFT (minutes directly)
def test_exgauss_kernel_has_the_right_mean_and_width(sigma, tau, over):
    k, origin = Pulse(kind="exgauss", sigma_bins=sigma, tau_bins=tau).kernel(over)
    assert k.sum() == pytest.approx(1.0) and np.all(k >= 0)
    offset = (np.arange(k.size) - origin) / over
    mean = (offset * k).sum()
    var = ((offset - mean) ** 2 * k).sum()
    # an ex-Gaussian's mean is the Gaussian centre + tau
    assert mean == pytest.approx(tau, abs=max(0.005, 1e-4 * tau))  # the tail is cut at 12 tau: 7e-5 tau short
    # variance sigma^2 + tau^2, plus the box of one sample (1/12 over^2) from averaging
    assert var == pytest.approx(sigma**2 + tau**2 + 1 / (12 * over**2), rel=0.03)


def test_table_pulse_kernel():
    k, origin = Pulse(kind="table", values=(0.0, 1.0, 3.0, 1.0), origin=2).kernel(1)
    np.testing.assert_allclose(k, [0, 0.2, 0.6, 0.2])
    assert origin == 2
    k4, origin4 = Pulse(kind="table", values=(0.0, 1.0, 3.0, 1.0), origin=2).kernel(4)
    assert origin4 == 10 and k4.sum() == pytest.approx(1.0)  # the middle of the arrival bin's four cells
    assert k4[origin4] == k4.max() and (k4 * (np.arange(k4.size) - origin4)).sum() == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("oversample", [3, 4, 8])
def test_a_table_pulse_bins_back_alike_at_any_oversampling(oversample):
    """Returns spread over a bin, put on the fine axis, convolved and binned back: the same mean response at any
    oversampling (the simulator's 8, the paper preset's 4, the fast preset's 1). The table's values read as point
    samples and interpolated put the peak 4 % lower at 8 than at 1 (10 % for a return at a bin's centre)."""
    pulse = sensor_preset("tmf8820").pulse

    def mean_response(over):
        kernel, origin = pulse.kernel(over)
        axis = FineAxis(64, over, 8)
        return np.mean([axis.to_bins(convolve_pulse(axis.splat(np.array([0]), np.array([t]), np.ones(1), 1),
                                                    kernel, origin))[0]
                        for t in np.linspace(20.0, 21.0, 48, endpoint=False)], axis=0)

    one, fine = mean_response(1), mean_response(oversample)
    assert fine.max() == pytest.approx(one.max(), rel=0.015)
    bins = np.arange(64)
    assert (fine @ bins) / fine.sum() == pytest.approx((one @ bins) / one.sum(), abs=0.01)


def _dict(**changes):
    d = sensor_preset("lcspc-sim").to_dict()
    d.update(changes)
    return json.loads(json.dumps(d))


@pytest.mark.parametrize("data,message", [
    (_dict(n_bins=2), "n_bins"),
    (_dict(bin_width_m=-1.0), "bin width"),
    (_dict(zero_bin=1e6), "zero bin"),
    (_dict(cycles=0), "cycles"),
    (_dict(background=float("nan")), "background"),
    (_dict(crosstalk=2.0), "crosstalk"),
    (_dict(max_count=2**40), "max_count"),
    (_dict(ignore_bins=[5000]), "ignore_bins"),
    (_dict(zones=[]), "at least one zone"),
    (_dict(zones=[{"kind": "hexagon"}]), "zone kind"),
    (_dict(zones=[{"kind": "cone", "half_angle_rad": 2.0}]), "half-angle"),
    (_dict(zones=[{"kind": "cone", "half_angle_rad": 0.2, "axis": [0, 0, -1]}]), "axis"),
    (_dict(zones=[{"kind": "rect", "tan_x": [0.2, 0.1], "tan_y": [0, 1]}]), "tan_x"),
    # A zone wider than 127 degrees: its rays, even in tangent, hit a small object at its centre whole or not at all.
    (_dict(zones=[{"kind": "rect", "tan_x": [-0.1, 0.1], "tan_y": [-9.9, 9.9]}]),
     r"tan_y bounds \(-9.9, 9.9\) must lie within \|tan\| < 2 \(edges under 63.4 degrees off the axis\)"),
    (_dict(zones=[{"kind": "cone", "half_angle_rad": 0.2, "gain": 0}]), "gain"),
    (_dict(zones=[{"kind": "cone", "half_angle_rad": 0.2, "colour": "red"}]), "unknown keys"),
    (_dict(pulse={"kind": "table", "values": [1, 2], "origin": 5}), "origin"),
    (_dict(pulse={"kind": "table", "values": [-1, 2], "origin": 0}), "pulse table"),
    (_dict(pulse={"kind": "exgauss", "sigma_bins": 0.0}), "sigma"),
    (_dict(pulse={"kind": "laser"}), "pulse kind"),
    (_dict(speed_of_light=3e8), "unknown keys"),
    ([1, 2, 3], "JSON object"),
    # Wrong JSON types (docs/capture_format.md), each named: "false" is truthy and turned pile-up on; 0.5 passed as a
    # bin index and crashed the fit; true counted as 1 cycle.
    (_dict(pileup="false"), "pileup = 'false' must be true or false"),
    (_dict(has_reference=1), "has_reference = 1 must be true or false"),
    (_dict(ignore_bins=[0.5]), r"ignore_bins = \[0.5\] must be a list of integers"),
    (_dict(ignore_bins=[True]), "ignore_bins"),
    (_dict(cycles=True), "cycles = True must be an integer"),
    (_dict(max_count=False), "max_count"),
    (_dict(n_bins=1024.0), "n_bins"),
    (_dict(signal_scale=True), "signal_scale = True must be a number"),
    (_dict(background="1e-4"), "background"),
    (_dict(name=5), "name"),
    (_dict(notes=None), "notes"),
    (_dict(zones=5), "zones must be a list"),
    (_dict(zones=[{"kind": "cone", "half_angle_rad": 0.2, "gain": True}]), "gain = True must be a number"),
    (_dict(zones=[{"kind": "cone", "half_angle_rad": 0.2, "axis": "up"}]), "axis"),
    (_dict(pulse={"kind": "table", "values": [1, 2], "origin": 0.5}), "origin = 0.5 must be an integer"),
    (_dict(pulse={"kind": "table", "values": [1, 2], "origin": True}), "origin = True must be an integer"),
    (_dict(pulse={"kind": "table", "values": [1, "2"], "origin": 0}), "values"),
    (_dict(pulse={"kind": "exgauss", "sigma_bins": True}), "sigma_bins"),
])
def test_validation_errors_are_one_line(data, message):
    with pytest.raises(SensorModelError, match=message) as info:
        SensorModel.from_dict(data)
    assert "\n" not in str(info.value)


def test_missing_keys_are_named():
    """Each in the manifest's words, as for zones and pulse (not the constructor's "missing 1 required positional
    argument")."""
    d = _dict()
    del d["pulse"]
    with pytest.raises(SensorModelError, match="^sensor model lacks 'pulse'$"):
        SensorModel.from_dict(d)
    d = _dict()
    del d["n_bins"]
    with pytest.raises(SensorModelError, match="^sensor model lacks 'n_bins'$"):
        SensorModel.from_dict(d)
    del d["cycles"]
    with pytest.raises(SensorModelError, match="^sensor model lacks 'n_bins', 'cycles'$"):
        SensorModel.from_dict(d)


def test_with_validates():
    model = sensor_preset("tmf8820")
    assert model.with_(cycles=10).cycles == 10
    with pytest.raises(SensorModelError):
        model.with_(signal_scale=-1.0)


def test_zone_masks_are_each_zones_own_test_whatever_the_kinds_in_between():
    """The rect zones share one division (the tangents); a cone between them is tested on its own."""
    torch = pytest.importorskip("torch")
    rects = sensor_preset("tmf8820").zones
    zones = (rects[0], Zone(kind="cone", half_angle_rad=0.3), rects[4], Zone(kind="cone", half_angle_rad=0.05,
                                                                              axis=(0.0, 0.6, 0.8)), rects[8])
    many = np.random.default_rng(2).normal(size=(5000, 3))
    many[:, 2] = np.abs(many[:, 2]) * 4  # mostly in front, so that every zone holds some
    many[:10, 2] = 0.0  # in the sensor's plane: held by no rect zone
    for rel in (many, torch.as_tensor(many)):
        masks = zone_masks(zones, rel)
        assert len(masks) == len(zones)
        for zone, mask in zip(zones, masks):
            own = zone.holds(rel)
            assert type(mask) is type(own) and mask.tolist() == own.tolist() and 0 < int(mask.sum()) < len(many)
    assert not any(bool(m[:10].any()) for m in zone_masks(rects, many))
