"""The simulator against closed forms: planes and spheres, pile-up, photon bookkeeping, edge cases, determinism."""

import inspect
import math

import numpy as np
import pytest
import trimesh

from spadscan.protocol import pileup, schedules
from spadscan.protocol.errors import SimulationError
from spadscan.protocol.schedules import look_at
from spadscan.protocol.sensor_model import Pulse, SensorModel, Zone
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import MIN_RANGE_M, SimSettings, Simulator

W = 1 / 800.0  # bin width (m)


def cone_sensor(half_angle_deg=15.0, **changes) -> SensorModel:
    base = SensorModel(name="test", n_bins=512, bin_width_m=W, zero_bin=2.0,
                       zones=(Zone(kind="cone", half_angle_rad=math.radians(half_angle_deg)),),
                       pulse=Pulse(kind="exgauss", sigma_bins=1.5, tau_bins=2.0), signal_scale=1.0,
                       background=1e-4, cycles=5000)
    return base.with_(**changes)


def plane(distance_m, tilt_deg=0.0, size_m=4.0):
    """A square facing -z at z = distance, tilted about the x axis through the point (0, 0, distance)."""
    m = trimesh.creation.box((size_m, size_m, 1e-3))
    m.apply_translation((0, 0, 0.5e-3))  # front face exactly at z = 0
    m.apply_transform(trimesh.transformations.rotation_matrix(math.radians(tilt_deg), (1, 0, 0)))
    m.apply_translation((0, 0, distance_m))
    return m


IDENTITY = np.eye(4)[None]


def plane_integral(d, half_angle_rad):
    """int cos_i / r^2 dOmega over a cone facing a plane at distance d: 2 pi / d^2 int u^3 du = pi (1 - c^4) / 2 d^2."""
    return math.pi * (1 - math.cos(half_angle_rad) ** 4) / (2 * d * d)


@pytest.mark.parametrize("d", [0.1 + 0.4 * W, 0.3 + 0.4 * W, 0.55 + 0.4 * W])
def test_plane_signal_matches_closed_form_and_falls_as_inverse_square(d):
    sim = Simulator(plane(d), cone_sensor(), SimSettings(albedo=0.7))
    h = sim.transient(IDENTITY)[0, 0]
    assert h.sum() == pytest.approx(0.7 * plane_integral(d, math.radians(15)), rel=2e-3)
    # the nearest point is straight ahead: the first return's bin is the plane's range; the returns end at the
    # cone's edge, d / cos(15 deg), and in between they fade as r^-5 (cos^3 / d^2 per solid angle, dOmega ~ r dr)
    first = math.floor(2.0 + d / W)
    assert np.flatnonzero(h)[0] == first
    assert np.flatnonzero(h)[-1] == math.floor(2.0 + d / math.cos(math.radians(15)) / W)
    assert h.argmax() in (first, first + 1)  # the first bin holds only the 0.6 bins after the plane's range
    assert np.all(np.diff(h[first + 1: np.flatnonzero(h)[-1]]) < 0)


def test_plane_signal_scales_with_power_and_signal_scale():
    sensor = cone_sensor(signal_scale=2.5, background=0.0)
    sim = Simulator(plane(0.3), sensor, SimSettings(power=3.0, albedo=0.5))
    sig = sim.signal_rates(IDENTITY)[0, 0]
    assert sig.sum() == pytest.approx(2.5 * 3.0 * 0.5 * plane_integral(0.3, math.radians(15)), rel=2e-3)
    assert sim.sensor.signal_scale == pytest.approx(7.5)  # the effective model records the power


@pytest.mark.parametrize("offset", [0.0, 0.25, 0.5, 0.8])
def test_sub_bin_arrival_time(offset):
    """A narrow cone sees one range; the pulse's centroid sits at its bin coordinate + the pulse's mean delay."""
    sensor = cone_sensor(half_angle_deg=0.5, background=0.0)
    d = (300 + offset) * W
    sim = Simulator(plane(d), sensor)
    sig = sim.signal_rates(IDENTITY)[0, 0]
    centres = np.arange(sig.size) + 0.5
    kernel, origin = sensor.pulse.kernel(8)
    delay = ((np.arange(kernel.size) - origin) / 8 * kernel).sum()  # mean of the pulse after arrival (bins)
    assert (centres * sig).sum() / sig.sum() == pytest.approx(2.0 + d / W + delay, abs=0.03)


def test_tilted_plane_falls_off_as_cosine():
    sensor = cone_sensor(half_angle_deg=1.0)
    base = Simulator(plane(0.3), sensor).transient(IDENTITY).sum()
    for tilt in (20.0, 45.0, 70.0):
        h = Simulator(plane(0.3, tilt), sensor).transient(IDENTITY).sum()
        assert h / base == pytest.approx(math.cos(math.radians(tilt)), rel=0.01)


def sphere_integral(dist, radius, n=200_001):
    """int cos_i / r^2 dOmega over a sphere seen whole from `dist` (quadrature over the angle from its centre)."""
    theta = np.linspace(0, math.asin(radius / dist), n)
    root = np.sqrt(np.maximum(radius**2 - (dist * np.sin(theta)) ** 2, 0))
    r = dist * np.cos(theta) - root
    f = 2 * np.pi * np.sin(theta) * (root / radius) / r**2
    return np.sum((f[1:] + f[:-1]) / 2 * np.diff(theta)), r


def test_sphere_matches_quadrature():
    dist, radius = 0.5 + 0.4 * W, 0.1
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    pose = look_at([0, -dist, 0], [0, 0, 0])[None]
    h = Simulator(mesh, cone_sensor(), SimSettings(rays_per_zone=8192)).transient(pose)[0, 0]
    total, r = sphere_integral(dist, radius)
    assert h.sum() == pytest.approx(total, rel=0.01)
    assert np.flatnonzero(h)[0] == math.floor(2.0 + (dist - radius) / W)
    # the range distribution: the mean range of the returns, weighted by their signal
    theta = np.linspace(0, math.asin(radius / dist), 200_001)
    root = np.sqrt(np.maximum(radius**2 - (dist * np.sin(theta)) ** 2, 0))
    weight = np.sin(theta) * root / r**2
    mean_bin = 2.0 + (weight * r).sum() / weight.sum() / W
    centres = np.arange(h.size) + 0.5
    assert (centres * h).sum() / h.sum() == pytest.approx(mean_bin, abs=0.3)


def test_rect_zones_match_tan_space_quadrature():
    sensor = sensor_preset("tmf8820")
    sim = Simulator(plane(0.4), sensor, SimSettings(rays_per_zone=4096))
    h = sim.transient(IDENTITY)[0]
    for zone, got in zip(sensor.zones, h.sum(axis=1)):
        x = np.linspace(*zone.tan_x, 801)
        y = np.linspace(*zone.tan_y, 801)
        xx, yy = np.meshgrid((x[1:] + x[:-1]) / 2, (y[1:] + y[:-1]) / 2)
        # cos_i = cos(theta) = 1/sqrt(q), r = d sqrt(q), dOmega = dx dy / q^1.5 with q = 1 + x^2 + y^2
        expect = (np.diff(x)[0] * np.diff(y)[0] / (1 + xx**2 + yy**2) ** 3).sum() / 0.4**2
        assert got == pytest.approx(expect, rel=3e-3)


def test_zone_gains_and_crosstalk():
    """A small target seen by the centre zone only: every other zone gets crosstalk x the total signal."""
    sensor = sensor_preset("tmf8820").with_(background=0.0)
    target = trimesh.creation.box((0.02, 0.02, 0.01))
    target.apply_translation((0, 0, 0.4))
    sig = Simulator(target, sensor).signal_rates(IDENTITY)[0].sum(axis=1)
    centre_gain = sensor.zones[4].gain
    direct = sig[4] / (1 + sensor.crosstalk)
    others = np.delete(sig, 4)
    np.testing.assert_allclose(others, sensor.crosstalk * direct, rtol=1e-9)
    no_x = Simulator(target, sensor.with_(crosstalk=0.0)).signal_rates(IDENTITY)[0].sum(axis=1)
    assert np.all(np.delete(no_x, 4) == 0) and no_x[4] == pytest.approx(direct)
    half = Simulator(target, sensor.with_(crosstalk=0.0, zones=tuple(
        z if i != 4 else Zone(kind="rect", tan_x=z.tan_x, tan_y=z.tan_y, gain=centre_gain / 2)
        for i, z in enumerate(sensor.zones)))).signal_rates(IDENTITY)[0].sum(axis=1)
    assert half[4] == pytest.approx(no_x[4] / 2)


def test_high_flux_moves_the_peak_earlier_as_coates_predicts():
    sensor = cone_sensor(background=1e-4)
    low = Simulator(plane(0.3), sensor, SimSettings(power=1e-3), seed=1)
    high = Simulator(plane(0.3), sensor, SimSettings(power=300.0), seed=1)
    rate_low, rate_high = low.expected_rates(IDENTITY)[0, 0], high.expected_rates(IDENTITY)[0, 0]
    assert rate_low.argmax() == rate_high.argmax()
    counts_high = high.frames(IDENTITY).hists[0, 0].astype(float)
    assert counts_high.argmax() < rate_high.argmax() - 1
    expect = sensor.cycles * pileup.detection_probabilities(rate_high)
    assert counts_high.argmax() == expect.argmax()
    peak = rate_high.argmax()
    # later bins are starved: what is left after the return is the background times the surviving fraction
    tail = slice(peak + 40, peak + 140)
    assert counts_high[tail].sum() < 0.01 * low.sensor.cycles * rate_high[tail].sum()
    np.testing.assert_allclose(counts_high.sum(), expect.sum(), rtol=0.02)


def test_counts_are_conserved():
    sim = Simulator(plane(0.3), cone_sensor(), SimSettings(power=5.0, cycles=7919), seed=3)
    fr = sim.frames(np.repeat(IDENTITY, 4, axis=0))
    assert fr.hists.dtype == np.uint32 and fr.hists.shape == (4, 1, 512)
    np.testing.assert_array_equal(fr.hists.sum(axis=-1) + fr.misses, 7919)


def test_saturating_flux_and_a_surface_1_mm_away_stay_finite():
    for d in (MIN_RANGE_M / 2, MIN_RANGE_M, 0.002):
        sim = Simulator(plane(d), cone_sensor(), SimSettings(power=1e6), seed=0)
        rates = sim.expected_rates(IDENTITY)
        assert np.all(np.isfinite(rates)) and rates.max() > 1e3
        fr = sim.frames(IDENTITY)
        assert fr.hists.sum() + fr.misses.sum() == 5000
        assert fr.hists[0, 0].argmax() <= 4  # everything piles up at the start of the histogram
    huge = Simulator(plane(0.3), cone_sensor(), SimSettings(power=1e9, ambient=1.0, cycles=10**10))
    fr = huge.frames(IDENTITY)
    assert np.all(np.isfinite(huge.expected_rates(IDENTITY))) and fr.hists.max() <= huge.sensor.max_count


def test_zero_signal_and_zero_ambient_stay_finite_and_positive():
    behind = plane(-0.3)  # behind the sensor: nothing in view
    sim = Simulator(behind, cone_sensor(), SimSettings(ambient=0.0))
    rates = sim.expected_rates(IDENTITY)
    assert np.all(rates > 0) and np.all(np.isfinite(rates))
    assert sim.frames(IDENTITY).hists.sum() == 0
    dark = Simulator(plane(0.3), cone_sensor(), SimSettings(power=0.0, ambient=0.0))
    assert dark.frames(IDENTITY).hists.sum() == 0


def test_grazing_plane_and_far_surfaces():
    sim = Simulator(plane(0.3, tilt_deg=89.9, size_m=20.0), cone_sensor())
    rates = sim.expected_rates(IDENTITY)
    assert np.all(np.isfinite(rates))
    far = Simulator(plane(10.0, size_m=50.0), cone_sensor())  # beyond the last bin (0.64 m): only background
    np.testing.assert_allclose(far.expected_rates(IDENTITY), 1e-4)


def test_deterministic_for_a_seed():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    poses = np.stack([look_at([0, -0.4, z], [0, 0, 0]) for z in (0.0, 0.1, 0.2)])
    a = Simulator(mesh, sensor_preset("tmf8820"), seed=5).frames(poses)
    b = Simulator(mesh, sensor_preset("tmf8820"), seed=5).frames(poses)
    c = Simulator(mesh, sensor_preset("tmf8820"), seed=6).frames(poses)
    np.testing.assert_array_equal(a.hists, b.hists)
    np.testing.assert_array_equal(a.reference, b.reference)
    assert not np.array_equal(a.hists, c.hists)
    # one pose at a time gives the same rates as a batch (the daemon renders pose by pose)
    sim = Simulator(mesh, sensor_preset("tmf8820"), seed=5)
    np.testing.assert_allclose(np.concatenate([sim.expected_rates(p[None]) for p in poses]),
                               sim.expected_rates(poses), rtol=1e-12)


def test_reference_channel():
    sensor = sensor_preset("tmf8820")
    fr = Simulator(plane(0.3), sensor).frames(np.repeat(IDENTITY, 2, axis=0))
    assert fr.reference.shape == (2, sensor.n_bins) and fr.reference.dtype == np.uint32
    assert abs(fr.reference[0].argmax() + 0.5 - (sensor.zero_bin + 2.3)) <= 1
    assert Simulator(plane(0.3), cone_sensor()).frames(IDENTITY).reference is None


@pytest.mark.parametrize("power", [0.3, 2.0])
def test_reference_channel_follows_the_laser_power(power):
    # The reference is the same laser through an internal path: its pulse scales with the power as the zones' do.
    sensor = sensor_preset("tmf8820")
    ref = {p: Simulator(plane(0.3), sensor, SimSettings(power=p), seed=3).frames(IDENTITY).reference[0].astype(float)
           for p in (1.0, power)}
    floor = {p: np.median(r) for p, r in ref.items()}
    pulse = {p: (r - floor[p]).clip(0).sum() for p, r in ref.items()}
    assert pulse[power] / pulse[1.0] == pytest.approx(power, rel=0.05)


def test_bad_inputs_raise():
    sim = Simulator(plane(0.3), cone_sensor())
    with pytest.raises(SimulationError, match=r"\(n, 4, 4\)"):
        sim.frames(np.eye(4))
    bad = np.eye(4)[None].copy()
    bad[0, 0, 0] = 2.0
    with pytest.raises(SimulationError, match="rigid"):
        sim.frames(bad)
    with pytest.raises(SimulationError, match="ambient"):
        Simulator(plane(0.3), cone_sensor(), SimSettings(ambient=-1.0))
    with pytest.raises(SimulationError, match="no triangles"):
        Simulator(trimesh.Trimesh(), cone_sensor())
    assert sim.frames(np.zeros((0, 4, 4))).hists.shape == (0, 1, 512)


# ---- captures and the command line -----------------------------------------------------------------------------
def test_simulate_capture_writes_a_complete_capture(tmp_path):
    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.simulator import simulate_capture

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    poses = fibonacci_hemisphere(10, 0.4)
    out = simulate_capture(mesh, sensor_preset("tmf8820"), poses, tmp_path / "cap", settings=SimSettings(power=2.0),
                           seed=4, chunk_size=4, scene={"builtin": "ball"}, schedule={"kind": "fibonacci"},
                           progress=False)
    reader = CaptureReader(out)
    assert reader.manifest["state"] == "complete"
    assert reader.manifest["scene"]["builtin"] == "ball" and reader.manifest["schedule"] == {"kind": "fibonacci"}
    assert reader.sensor.signal_scale == pytest.approx(2.0 * sensor_preset("tmf8820").signal_scale)
    chunks = [reader.read_chunk(name) for name in reader.chunk_names()]
    assert [len(c.meta) for c in chunks] == [4, 4, 2]
    hists = np.concatenate([c.hists for c in chunks])
    np.testing.assert_allclose(np.concatenate([c.poses for c in chunks]), poses)
    assert all(c.reference is not None for c in chunks)
    # the same seed renders the same counts through the library call
    again = Simulator(mesh, sensor_preset("tmf8820"), SimSettings(power=2.0), seed=4)
    expect = np.concatenate([again.frames(poses[i: i + 4]).hists for i in range(0, 10, 4)])
    np.testing.assert_array_equal(hists, expect)


def test_simulate_command(tmp_path, capsys):
    from spadscan.cli import main
    from spadscan.protocol.capture_reader import CaptureReader

    mesh_path = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=2, radius=0.08).export(mesh_path)
    out = tmp_path / "cap"
    args = [str(mesh_path), "--out", str(out), "--views", "12", "--schedule", "rings", "--rings", "3",
            "--min-elevation", "10", "--max-elevation", "60", "--radius", "0.3", "--target", "0", "0", "0.01",
            "--jitter-deg", "3", "--ambient", "1e-5", "--power", "2", "--cycles", "1000", "--seed", "2",
            "--no-progress"]
    assert main(["simulate", *args]) == 0
    reader = CaptureReader(out)
    m = reader.manifest
    assert m["state"] == "complete" and m["scene"]["mesh"].endswith("ball.obj")
    assert m["schedule"]["kind"] == "rings" and m["schedule"]["per_ring"] == 4 and m["schedule"]["jitter_deg"] == 3
    assert reader.sensor.cycles == 1000 and reader.sensor.background == 1e-5
    hists = np.concatenate([reader.read_chunk(n).hists for n in reader.chunk_names()])
    assert hists.shape == (12, 1, 1024) and hists.sum(axis=-1).max() <= 1000
    # one-line errors: the folder already holds a capture, a missing mesh, a bad schedule
    assert main(["simulate", *args]) == 1
    assert main(["simulate", str(tmp_path / "none.obj"), "--out", str(tmp_path / "x")]) == 1
    assert main(["simulate", str(mesh_path), "--out", str(tmp_path / "y"), "--views", "10", "--schedule", "rings",
                 "--rings", "3"]) == 1
    err = capsys.readouterr().err
    assert "already holds a capture" in err and "no such mesh file" in err and "multiple of --rings" in err
    assert "Traceback" not in err


def test_simulate_rings_by_default_keep_every_view_apart(tmp_path):
    """The spiral's band reaches 90 deg; a ring there would be one viewpoint: the rings get a band of their own."""
    from spadscan.cli import main
    from spadscan.commands.simulate import RINGS_BAND
    from spadscan.protocol.capture_reader import CaptureReader

    band = inspect.signature(schedules.elevation_rings).parameters
    assert RINGS_BAND == (band["min_elevation_deg"].default, band["max_elevation_deg"].default)
    mesh_path = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=1, radius=0.05).export(mesh_path)
    args = [str(mesh_path), "--views", "16", "--schedule", "rings", "--radius", "0.3", "--no-progress"]
    assert main(["simulate", *args, "--out", str(tmp_path / "a")]) == 0
    reader = CaptureReader(tmp_path / "a")
    positions = np.concatenate([reader.read_chunk(n).poses for n in reader.chunk_names()])[:, :3, 3]
    assert len(np.unique(np.round(positions, 6), axis=0)) == 16
    assert reader.manifest["schedule"]["max_elevation_deg"] == RINGS_BAND[1]
    assert main(["simulate", *args, "--out", str(tmp_path / "b"), "--max-elevation", "90"]) == 1
    assert not (tmp_path / "b").exists()


def test_simulate_builtin_scene(tmp_path):
    from spadscan.cli import main
    from spadscan.protocol import scenes
    from spadscan.protocol.capture_reader import CaptureReader

    name = sorted(scenes.BUILTIN_SCENES)[0]
    assert main(["simulate", f"builtin:{name}", "--out", str(tmp_path / "b"), "--views", "4", "--no-progress"]) == 0
    assert CaptureReader(tmp_path / "b").manifest["scene"]["builtin"] == name
    assert main(["simulate", "builtin:no-such-scene", "--out", str(tmp_path / "c")]) == 1


@pytest.mark.parametrize("option, value, message", [
    ("--seed", "-1", "--seed -1 must be an integer >= 0"),
    ("--jitter-deg", "-5", "--jitter-deg -5 must be >= 0 degrees"),
    ("--jitter-deg", "nan", "--jitter-deg nan must be >= 0 degrees"),
    ("--power", "0", "--power 0 must be > 0"),
    ("--power", "-2", "--power -2 must be > 0"),
    ("--radius", "inf", "--radius inf m must be a finite distance > 0"),
])
def test_simulate_refuses_options_that_make_no_physical_sense(tmp_path, capsys, option, value, message):
    from spadscan.cli import main

    out = tmp_path / "cap"
    assert main(["simulate", "builtin:sphere", "--out", str(out), "--views", "4", "--no-progress",
                 option, value]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"spadscan: error: {message}") and err.count("\n") == 1
    assert not out.exists(), "checked before anything is written"


def test_a_negative_seed_is_a_simulation_error():
    for seed in (-1, 1.5, True):
        with pytest.raises(SimulationError, match="must be an integer >= 0"):
            Simulator(plane(0.3), cone_sensor(), seed=seed)


def test_simulate_on_a_full_disk_says_so_and_leaves_an_aborted_capture(tmp_path, capsys, monkeypatch):
    import spadscan.protocol.capture_writer as cw
    from spadscan.cli import main
    from spadscan.protocol.capture_reader import CaptureReader

    real = cw.save_npy_durable

    def fill_up(path, array):  # the first chunk fits; then np.save runs out of room as it does on a full disk
        if path.parent.name == ".tmp-chunk-000001":
            raise OSError(f"{array.nbytes} requested and 3040 written")
        real(path, array)

    monkeypatch.setattr(cw, "save_npy_durable", fill_up)
    out = tmp_path / "cap"
    args = ["simulate", "builtin:sphere", "--out", str(out), "--views", "8", "--chunk-size", "4", "--no-progress"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"spadscan: error: {out / '.tmp-chunk-000001'}/")
    assert "the disk is full" in err
    m = CaptureReader(out).manifest
    assert m["state"] == "aborted" and m["reason"].startswith("simulation failed: ")
    assert not [p for p in out.iterdir() if p.name.startswith(".tmp-")]
    monkeypatch.setattr(cw, "save_npy_durable", real)
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "already holds a capture that was not finished (state 'aborted'" in err and "delete the folder" in err


def test_sigterm_ends_a_simulation_as_ctrl_c_does(tmp_path):
    """`kill` (SIGTERM) mid-simulation: exit 130 and a manifest that says the capture was interrupted, not one
    left 'running' as if it were still being written."""
    import json
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "cap"
    proc = subprocess.Popen([sys.executable, "-m", "spadscan.cli", "simulate", "builtin:sphere", "--out", str(out),
                             "--views", "4000", "--chunk-size", "4", "--no-progress"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not list(out.glob("chunk-*")) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert proc.poll() is None, "the simulation ended before it could be stopped"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == 130 and err.strip().splitlines()[-1] == "spadscan: interrupted"
    manifest = json.loads((out / "scan.json").read_text())
    assert manifest["state"] == "aborted" and "interrupted" in manifest["reason"]


def test_views_that_see_nothing_of_the_mesh_are_said(tmp_path, capsys):
    from spadscan.cli import main

    far = trimesh.creation.icosphere(radius=0.05).apply_translation([5.0, 0, 0])
    far.export(tmp_path / "far.ply")
    assert main(["simulate", str(tmp_path / "far.ply"), "--out", str(tmp_path / "a"), "--views", "6",
                 "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "warning: none of the 6 views see the mesh" in err and "[4.95, -0.05, -0.05]" in err
    # A target above the mesh: the views near the horizon look past it, those from above see it.
    assert main(["simulate", "builtin:sphere", "--out", str(tmp_path / "b"), "--views", "16", "--no-progress",
                 "--target", "0", "0", "0.3", "--radius", "0.3"]) == 0
    line = next(x for x in capsys.readouterr().err.splitlines() if x.startswith("warning:"))
    blind = int(line.split()[1])
    assert 0 < blind < 16 and line.startswith(f"warning: {blind} of 16 views see nothing of the mesh (")
    assert main(["simulate", "builtin:sphere", "--out", str(tmp_path / "c"), "--views", "6", "--no-progress"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_a_mesh_read_as_millimetres_is_said_and_recorded(tmp_path, capsys):
    import json

    from spadscan.cli import main

    trimesh.creation.icosphere(radius=40.0).apply_translation([0, 0, 40.0]).export(tmp_path / "mm.obj")
    assert main(["simulate", str(tmp_path / "mm.obj"), "--out", str(tmp_path / "a"), "--views", "4",
                 "--no-progress"]) == 0
    assert f"{tmp_path / 'mm.obj'}: read as millimetres" in capsys.readouterr().err
    scene = json.loads((tmp_path / "a" / "scan.json").read_text())["scene"]
    assert scene["mesh_units"] == "mm"
    trimesh.creation.icosphere(radius=0.04).export(tmp_path / "m.obj")
    assert main(["simulate", str(tmp_path / "m.obj"), "--out", str(tmp_path / "b"), "--views", "4",
                 "--no-progress"]) == 0
    assert "millimetres" not in capsys.readouterr().err
    assert "mesh_units" not in json.loads((tmp_path / "b" / "scan.json").read_text())["scene"]


def test_a_capture_is_not_written_among_other_files(tmp_path, capsys):
    from spadscan.cli import main

    out = tmp_path / "notes"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert main(["simulate", "builtin:sphere", "--out", str(out), "--views", "4", "--no-progress"]) == 1
    assert capsys.readouterr().err == (f"spadscan: error: {out}: holds other files (notes.txt); a capture needs a "
                                       f"new or empty folder\n")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["simulate", "builtin:sphere", "--out", str(empty), "--views", "4", "--no-progress"]) == 0


def test_rings_without_the_rings_schedule_is_refused_and_the_help_names_the_builtin_scenes(tmp_path, capsys):
    from spadscan.cli import main
    from spadscan.protocol.scenes import BUILTIN_SCENES

    assert main(["simulate", "builtin:sphere", "--out", str(tmp_path / "a"), "--views", "4", "--rings", "3"]) == 1
    assert capsys.readouterr().err == "spadscan: error: --rings 3 is for --schedule rings (the fibonacci spiral has " \
                                      "none)\n"
    assert not (tmp_path / "a").exists()
    assert main(["simulate", "builtin:sphere", "--out", str(tmp_path / "b"), "--views", "8", "--schedule", "rings",
                 "--no-progress"]) == 0  # the default ring count
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    listing = capsys.readouterr().out.split("built-in scenes (builtin:NAME):", 1)[1]
    assert all(f"    {name} " in listing for name in BUILTIN_SCENES)
    assert "validation split" in listing and "tuning split" in listing


# ---- the table -------------------------------------------------------------------------------------------------------
def far_ball():
    """A small ball far outside every view of the table tests: the simulator needs a mesh."""
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.01)
    ball.apply_translation([50.0, 0, 0])
    return ball


def down_from(height_m, tilt_deg=0.0):
    """A sensor at (0, 0, height_m) looking down, tilted by tilt_deg towards +y."""
    t = math.radians(tilt_deg)
    return look_at([0, 0, height_m], [0, height_m * math.tan(t), 0])[None]


@pytest.mark.parametrize("height, table_z", [(0.3 + 0.4 * W, 0.0), (0.25 + 0.4 * W, -0.1)])
def test_table_returns_from_where_its_plane_is_with_the_closed_form_strength(height, table_z):
    from spadscan.protocol.sim_table import SimTable

    sim = Simulator(far_ball(), cone_sensor(), SimSettings(), table=SimTable(height_m=table_z, albedo=0.08))
    h = sim.transient(down_from(height))[0, 0]
    d = height - table_z
    assert h.sum() == pytest.approx(0.08 * plane_integral(d, math.radians(15)), rel=2e-3)
    assert np.flatnonzero(h)[0] == math.floor(2.0 + d / W)
    assert np.flatnonzero(h)[-1] == math.floor(2.0 + d / math.cos(math.radians(15)) / W)
    # seen obliquely, the boresight meets the table at d / cos(tilt), and the return weakens with the incidence
    oblique = Simulator(far_ball(), cone_sensor(half_angle_deg=0.5), table=SimTable(table_z, 0.08))
    straight = oblique.transient(down_from(height))[0, 0].sum()
    tilted = oblique.transient(down_from(height, 40.0))[0, 0]
    centres = np.arange(tilted.size) + 0.5
    assert (centres * tilted).sum() / tilted.sum() == pytest.approx(2.0 + d / math.cos(math.radians(40)) / W, abs=0.6)
    assert tilted.sum() / straight == pytest.approx(math.cos(math.radians(40)) ** 3, rel=0.01)  # cos / r^2


def test_table_strength_scales_with_its_albedo_alone():
    from spadscan.protocol.sim_table import SimTable

    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    ball.apply_translation([0, 0, 0.05])
    pose = down_from(0.4, 10.0)
    parts = {a: Simulator(ball, cone_sensor(), SimSettings(albedo=0.5), table=SimTable(0.0, a)).transient(pose)[0, 0]
             for a in (0.0, 0.05, 0.1)}
    table_05, table_10 = parts[0.05] - parts[0.0], parts[0.1] - parts[0.0]
    assert table_05.sum() > 0
    np.testing.assert_allclose(table_10, 2 * table_05, rtol=1e-9, atol=1e-12)
    # the ball is the same in all three: its return (nearer than the table under the sensor) does not change
    ball_bins = slice(0, math.floor(2.0 + 0.29 / W))
    np.testing.assert_array_equal(parts[0.0][ball_bins], parts[0.1][ball_bins])


def test_the_object_hides_the_table_behind_it():
    from spadscan.protocol.sim_table import SimTable

    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    ball.apply_translation([0, 0, 0.05])
    pose = down_from(0.3)
    table = SimTable(0.0, 0.1)
    alone = Simulator(far_ball(), cone_sensor(), table=table).transient(pose)[0, 0]
    both = Simulator(ball, cone_sensor(), SimSettings(albedo=0.0), table=table).transient(pose)[0, 0]
    # the ball (black here) covers a cone of half-angle asin(0.05 / 0.25) around the boresight: the table's returns
    # from inside it, the nearest ones, are gone; those from outside it are unchanged
    hidden = math.asin(0.05 / 0.25)
    edge_bin = math.floor(2.0 + 0.3 / math.cos(hidden) / W)
    assert both[: edge_bin - 1].sum() == 0 and alone[: edge_bin - 1].sum() > 0
    np.testing.assert_allclose(both[edge_bin + 2:], alone[edge_bin + 2:])


def test_table_is_a_finite_square_opaque_from_both_sides():
    from spadscan.protocol.sim_table import SimTable

    sensor = cone_sensor(half_angle_deg=2.0)
    table = SimTable(0.0, 0.1, half_size_m=0.5)
    sim = Simulator(far_ball(), sensor, table=table)
    over = look_at([0.3, 0, 0.2], [0.3, 0, 0])[None]
    beyond = look_at([0.8, 0, 0.2], [0.8, 0, 0])[None]
    under = look_at([0.3, 0, -0.2], [0.3, 0, 0])[None]
    h = sim.transient(np.concatenate([over, beyond, under]))[:, 0]
    assert h[0].sum() > 0 and h[1].sum() == 0
    np.testing.assert_allclose(h[2], h[0])  # from below: the same plane, the same range


@pytest.mark.parametrize("changes, message", [
    ({"albedo": -0.1}, "table albedo = -0.1"), ({"height_m": float("nan")}, "table height_m = nan"),
    ({"half_size_m": 0.0}, "table half_size_m = 0.0"),
])
def test_a_bad_table_is_a_one_line_error(changes, message):
    from spadscan.protocol.sim_table import SimTable

    with pytest.raises(SimulationError) as info:
        Simulator(far_ball(), cone_sensor(), table=SimTable(**changes))
    assert message in str(info.value) and "\n" not in str(info.value)


def test_simulate_with_a_table_records_it_as_a_table_to_find_and_the_floor_finds_it(tmp_path, capsys):
    from spadscan.cli import main
    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.worker.baselines.floor import scene_floor

    out = tmp_path / "cap"
    assert main(["simulate", "builtin:pyramid", "--out", str(out), "--sensor", "tmf8820", "--table",
                 "--table-albedo", "0.3", "--table-height", "-0.02", "--views", "24", "--schedule", "rings",
                 "--rings", "3", "--min-elevation", "36", "--max-elevation", "83", "--radius", "0.3",
                 "--rays-per-zone", "64", "--no-progress"]) == 0
    assert "on a table at z = -0.02 m (albedo 0.3)" in capsys.readouterr().err
    data = CaptureReader(out).load()
    scene = data.manifest["scene"]
    assert scene["table"] is True
    assert scene["simulated_table"] == {"z": -0.02, "albedo": 0.3, "half_size_m": 1.0}
    height, source = scene_floor(data)  # the table search of measured captures, on the histograms alone
    assert source == "the table, found in the histograms" and height == pytest.approx(-0.02, abs=0.015)


@pytest.mark.parametrize("height, mesh", [("0.3", "builtin:demo"), ("20", "builtin:demo"), (None, "sunk")])
def test_a_table_above_the_objects_lowest_point_is_refused(tmp_path, capsys, height, mesh):
    """The demo stands 0..0.2 m: a table at 0.3 m (or 20 m, millimetres typed as metres) hung over it, and a mesh
    reaching 5 cm below the default table at 0 was cut by it; both wrote a 'table' capture."""
    from spadscan.cli import main

    if mesh == "sunk":
        mesh = str(tmp_path / "sunk.ply")
        trimesh.creation.box([0.1, 0.1, 0.1]).export(mesh)  # centred on the origin: 5 cm under z = 0
    given = [] if height is None else ["--table-height", height]
    assert main(["simulate", mesh, "--out", str(tmp_path / "c"), "--views", "4", "--table", *given,
                 "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("spadscan: error: ") and err.count("\n") == 1, err
    assert "above the object's lowest point" in err and "--table-height" in err
    assert ("--table-height -0.05" in err) if height is None else ("--table-height 0 (metres)" in err), err
    assert not (tmp_path / "c").exists()


def test_an_object_floating_above_its_table_is_warned_about(tmp_path, capsys):
    from spadscan.cli import main

    assert main(["simulate", "builtin:sphere", "--out", str(tmp_path / "c"), "--views", "2", "--table",
                 "--table-height", "-0.05", "--rays-per-zone", "16", "--no-progress"]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert warnings == ["spadscan: warning: the object's lowest point (z = 0 m) floats 50 mm above the table "
                        "(--table-height -0.05): it does not stand on it (--table-height 0 puts it there, metres)"]
    assert main(["simulate", "builtin:sphere", "--out", str(tmp_path / "d"), "--views", "2", "--table",
                 "--table-height", "0.002", "--rays-per-zone", "16", "--no-progress"]) == 0
    assert "warning" not in capsys.readouterr().err  # a hair above the feet: the mesh's rounding, not a mistake


@pytest.mark.parametrize("option", [["--table-albedo", "0.2"], ["--table-height", "0.1"]])
def test_table_options_without_a_table_are_refused(tmp_path, capsys, option):
    from spadscan.cli import main

    assert main(["simulate", "builtin:sphere", "--out", str(tmp_path / "c"), "--views", "4", *option]) == 1
    err = capsys.readouterr().err
    assert err == f"spadscan: error: {option[0]} {option[1]} is for a table: add --table\n"
    assert not (tmp_path / "c").exists()


def test_a_power_beyond_the_sensor_models_limit_names_power():
    """--power 1e9 passed the settings' check, then failed naming signal_scale, which the user never set."""
    with pytest.raises(SimulationError, match=r"power = 1e\+09 is too much for sensor 'lcspc-sim': at most 8\.9"):
        Simulator(trimesh.creation.icosphere(), sensor_preset("lcspc-sim"), SimSettings(power=1e9))
