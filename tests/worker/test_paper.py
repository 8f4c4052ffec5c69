"""The `paper` preset: capture loading, the MLP field, the model protocol, and a short run that must improve."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import trimesh

from spadscan.cli import main as cli_main
from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.errors import CaptureError, ConfigError, SpadscanError
from spadscan.protocol.scenes import builtin_scene
from spadscan.protocol.schedules import fibonacci_hemisphere, look_at
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.sim_table import SimTable
from spadscan.protocol.simulator import SimSettings, Simulator, simulate_capture
from spadscan.worker.recon.config import PRESET_NAMES, with_overrides
from spadscan.worker.recon.errors import ReconstructionError
from spadscan.worker.recon.model_api import ReconModel, RunPlan
from spadscan.worker.recon.paper.config import MLPFieldConfig
from spadscan.worker.recon.paper.field import MLPField
from spadscan.worker.recon.paper.loss import hist_nll
from spadscan.worker.recon.paper.model import make_paper_model
from spadscan.worker.recon.paper.render import SphereField
from spadscan.worker.recon.presets import PRESETS, preset_config
from spadscan.worker.pulse import KERNEL_BEFORE
from spadscan.worker.recon.scene_data import load_scene
from worker_helpers import PAPER_SMALL, sensor_forward


pytestmark = pytest.mark.usefixtures("one_thread")


def box_mesh():
    import trimesh

    mesh = trimesh.creation.box(extents=(0.08, 0.06, 0.1))
    mesh.apply_translation([0.01, 0.0, 0.05])
    return mesh


@pytest.fixture(scope="module")
def box_capture(tmp_path_factory):
    """8 simulated views of a box from 0.3 m (LCSPCData's simulated sensor)."""
    path = tmp_path_factory.mktemp("cap") / "box"
    poses = fibonacci_hemisphere(8, 0.3, target=(0, 0, 0.05), min_elevation_deg=10)
    simulate_capture(box_mesh(), sensor_preset("lcspc-sim"), poses, path, settings=SimSettings(rays_per_zone=1024),
                     progress=False)
    return path


def small_paper(**extra):
    return with_overrides(preset_config("paper"), {**PAPER_SMALL, **extra})


def fit_error(model, scene) -> float:
    rendered = model.render_histograms(range(scene.n_views))
    counts = scene.counts.double().numpy()
    return float(((rendered - counts) ** 2).sum() / (counts ** 2).sum())


@pytest.mark.slow
def test_short_paper_run_lowers_loss_fit_error_and_chamfer(box_capture):
    from spadscan.worker.metrics import mesh_metrics

    scene = load_scene(box_capture)
    model = make_paper_model(scene, small_paper(), "cpu", RunPlan(steps=40, budget_s=None, seed=0))
    gt = box_mesh()
    chamfer0 = mesh_metrics(model.extract_mesh(48), gt, n_points=5000).chamfer_mm
    fit0 = fit_error(model, scene)
    losses = [model.step()["loss"] for _ in range(40)]
    chamfer1 = mesh_metrics(model.extract_mesh(48), gt, n_points=5000).chamfer_mm
    fit1 = fit_error(model, scene)
    assert np.all(np.isfinite(losses))
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:5])
    assert fit1 < 0.5 * fit0
    assert chamfer1 < 0.7 * chamfer0, f"Chamfer went from {chamfer0:.1f} mm to {chamfer1:.1f} mm"


def test_paper_model_follows_the_protocol(box_capture):
    scene = load_scene(box_capture)
    model = make_paper_model(scene, small_paper(), "cpu", RunPlan(steps=2, budget_s=None))
    assert isinstance(model, ReconModel)
    out = model.step()
    assert {"loss", "data", "eikonal"} <= set(out) and np.isfinite(out["loss"])
    hist = model.render_histograms([0, 3])
    assert hist.shape == (2, 1, scene.sensor.n_bins) and np.all(np.isfinite(hist)) and np.all(hist >= 0)
    # Deterministic renders, as the model says (the fit check then renders each view once).
    assert model.stochastic_render is False and np.array_equal(model.render_histograms([0, 3]), hist)
    mesh = model.extract_mesh(32)
    normals = np.asarray(mesh.vertex_normals)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    # Normals from the SDF gradient point outward: away from the mesh's centre on this blob.
    outward = np.einsum("ij,ij->i", normals, mesh.vertices - mesh.vertices.mean(0))
    assert np.mean(outward > 0) > 0.9
    summary = model.summary()
    assert summary["steps"] == 1 and json.dumps(summary)


def test_mlp_field_starts_as_a_sphere_inside_the_scene():
    torch.manual_seed(0)
    field = MLPField(MLPFieldConfig(), torch.tensor([0.1, 0.0, 0.2]), 0.3)
    dirs = torch.randn(2000, 3)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    centre = torch.tensor([0.1, 0.0, 0.2])
    with torch.no_grad():
        inside = field.sdf(centre[None])[0]
        boundary = field.sdf(centre + 0.3 * dirs)
        half = field.sdf(centre + 0.15 * dirs)
    # A closed surface inside the scene sphere (the init is a sphere only on average: allow a few % of directions).
    assert inside < 0 and float((boundary > 0).float().mean()) > 0.95 and float(boundary.mean()) > 0.05
    assert abs(float(half.mean())) < 0.05  # crossing near init_radius = 0.5 of the scene radius
    with pytest.raises(ReconstructionError, match="width"):
        MLPField(MLPFieldConfig(width=16), centre, 0.3)


def test_registry_and_overrides():
    cfg = preset_config("paper")
    assert (cfg.rays.rays_per_view, cfg.rays.importance_rays_per_view) == (512, 64)
    assert (cfg.rays.samples_per_ray, cfg.rays.importance_samples) == (256, 32)
    assert (cfg.optim.lr, cfg.optim.nominal_steps, cfg.loss.eikonal_weight) == (5e-4, 300_000, 0.1)
    assert (cfg.field.layers, cfg.field.width, cfg.field.frequencies) == (8, 256, 6)
    assert json.dumps(cfg.to_dict())
    with pytest.raises(ReconstructionError, match="unknown preset"):
        preset_config("slow")
    with pytest.raises(ReconstructionError, match="no field"):
        with_overrides(cfg, {"rays.samples": 3})
    assert preset_config("paper").rays.samples_per_ray == 256  # overrides never touch the registry's copy


@pytest.mark.parametrize("preset, key, value, message", [
    ("fast", "preset", "paper", "fixed by the preset"),
    ("paper", "model_factory", "os:system", "preset 'paper' does not use it"),
    ("paper", "dtype", "float16", "'float16' is not one of float32, float64"),
    ("paper", "loss.kind", "foo", "'foo' is not one of l2, nll"),
    ("fast", "dtype", "float64", "preset 'fast' does not use it"),
    ("fast", "loss.kind", "l2", "preset 'fast' does not use it"),
    ("fast", "loss.eikonal_points", 64, "preset 'fast' does not use it"),
    ("fast", "rays.samples_per_ray", 64, "preset 'fast' has no section 'rays'"),
    ("paper", "parts.openings.enabled", False, "preset 'paper' has no section 'parts'"),
    ("paper", "early_stop", True, "preset 'paper' does not use it"),
    ("fast", "albedo_init", 0.5, "preset 'fast' does not use it"),
    ("fast", "loss.tv_weight", 0.1, "has moved it: loss.smooth_weight"),
    ("fast", "schedule.grad_blur_passes", 0, "has moved it: parts.blur.passes"),
    ("fast", "field.refine_after_steps", 0, "parts.refinement.enabled=false"),
    ("fast", "parts.nothing.enabled", False, "parts has no section 'nothing'"),
    ("fast", "mesh_resolution", 4, "mesh_resolution 4 must be in \\[8, 1024\\]"),
    ("fast", "schedule", None, "a config section; set its fields"),
    ("fast", "mesh_resolution", None, "the field takes no null"),
    ("paper", "default_budget_s", "abc", "must be null or a finite number > 0"),
    ("paper", "default_budget_s", -5, "must be null or a finite number > 0"),
    ("paper", "rays.samples_per_ray", 1, "^rays.samples_per_ray 1 must be an integer >= 2$"),
    ("paper", "rays.views_per_batch", 0, "^rays.views_per_batch 0 must be an integer >= 1$"),
    ("paper", "rays.rays_per_view", 0, "^rays.rays_per_view 0 must be an integer >= 1$"),
    ("paper", "sharpness.init", 0, "^sharpness.init 0.0 must be > 0$"),
    ("paper", "albedo_init", 0, "^albedo_init 0.0 must be > 0$"),
    ("paper", "optim.nominal_steps", 0, "^optim.nominal_steps 0 must be an integer >= 1$"),
])
def test_overrides_that_would_not_do_what_they_say_are_refused(preset, key, value, message):
    with pytest.raises(SpadscanError, match=message):
        with_overrides(preset_config(preset), {key: value})


def test_paper_values_the_model_cannot_run_with_are_a_config_error():
    with pytest.raises(ConfigError):  # the type the CLI prints as one line, raised before a capture is loaded
        with_overrides(preset_config("paper"), {"rays.samples_per_ray": 1})


def test_no_random_eikonal_points_runs_on_the_ray_samples_alone(box_capture, tmp_path):
    scene = load_scene(box_capture)
    model = make_paper_model(scene, small_paper(**{"loss.eikonal_points": 0}), "cpu", RunPlan(steps=2, budget_s=None))
    out = model.step()
    # No random-point term: the loss is the data term and the Eikonal term of the ray samples, nothing else.
    assert np.isfinite(out["loss"]) and out["loss"] == pytest.approx(out["data"] + 0.1 * out["eikonal"], rel=1e-9)
    # On measured data the TV term is taken at those points: refused in one line unless it is off too.
    sensor = sensor_preset("tmf8820")
    poses = np.stack([look_at(np.array([0.3, 0.0, 0.2]), np.zeros(3))])
    cap = write_capture(tmp_path / "real", sensor, np.random.default_rng(0).poisson(150, (1, 9, 128)).astype(np.uint32),
                        poses, scene={"table": True, "real": True})
    real = load_scene(cap)
    with pytest.raises(ReconstructionError, match="set loss.tv_weight=0 too"):
        make_paper_model(real, small_paper(**{"loss.eikonal_points": 0}), "cpu", RunPlan(steps=2, budget_s=None))
    model = make_paper_model(real, small_paper(**{"loss.eikonal_points": 0, "loss.tv_weight": 0.0}), "cpu",
                             RunPlan(steps=2, budget_s=None))
    assert np.isfinite(model.step()["loss"])
    assert not model.terms.tv, "TV without a weight is no term of the fit: the report lists it as left out"
    assert make_paper_model(real, small_paper(), "cpu", RunPlan(steps=2, budget_s=None)).terms.tv


def test_importance_rays_are_unbiased_at_silhouettes(box_capture):
    """The solid angle of a small ball in view 0, as the training rays' weights estimate it (sum of the weights of
    the rays that hit it), averaged over draws, is the exact one. Importance probabilities taken from the same rays
    they weight fell 5.5 % short here (a cell whose ray hit got a small weight): the hard edge shows what a smooth
    integrand hides."""
    scene = load_scene(box_capture, dtype=torch.float64)
    cfg = small_paper(**{"dtype": "float64", "rays.samples_per_ray": 16, "rays.importance_samples": 0})
    model = make_paper_model(scene, cfg, "cpu", RunPlan(steps=1, budget_s=None))
    pose = scene.poses[0].double()
    c, r = pose[:3, 3] + 0.3 * pose[:3, 2], 0.05  # on the boresight, 0.3 m out: 9.6 deg of the 15 deg cone
    model.field = SphereField(c, r)
    with torch.no_grad():
        model.log_s.fill_(math.log(1e4))
    est = []
    for _ in range(300):
        b = model.make_batch(torch.tensor([0]), train=True)
        o, d = b.origins.reshape(-1, 3), b.dirs.reshape(-1, 3)
        oc = o - c
        along = (oc * d).sum(-1)
        est.append(float((b.weight.reshape(-1) * (along ** 2 - (oc * oc).sum(-1) + r * r > 0)).sum()))
    est = np.array(est)
    assert model.n_imp_rays > 0 and b.n_rays > model.grid.n_cells  # importance rays were drawn
    exact = 2 * math.pi * (1 - math.sqrt(1 - (r / 0.3) ** 2))
    assert abs(est.mean() - exact) < 4 * est.std() / math.sqrt(len(est)), f"{est.mean() / exact - 1:+.1%}"


def test_table_rays_that_miss_the_scene_sphere_return_the_table(tmp_path):
    """Low views of a small ball on a table: many rays meet the table outside the scene sphere. The model's render
    of the true scene (ball, table height and albedo) matches the simulator zone by zone; without those rays a zone
    lost up to a third of its signal."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.04)
    ball.apply_translation([0.0, 0.0, 0.04])
    table = SimTable(height_m=0.0)
    target = np.array([0.0, 0.0, 0.04])
    poses = np.stack([look_at(target + 0.3 * np.array([math.cos(a) * math.cos(e), math.sin(a) * math.cos(e),
                                                       math.sin(e)]), target)
                      for a, e in ((0.0, math.radians(15)), (2.0, math.radians(27)), (4.0, math.radians(40)))])
    sensor = sensor_preset("tmf8820")
    cap = simulate_capture(ball, sensor, poses, tmp_path / "low", settings=SimSettings(rays_per_zone=64),
                           progress=False, table=table)
    scene = load_scene(cap, dtype=torch.float64)
    cfg = small_paper(**{"dtype": "float64", "rays.rays_per_view": 512, "rays.importance_samples": 0})
    model = make_paper_model(scene, cfg, "cpu", RunPlan(steps=1, budget_s=None))
    model.field = SphereField(target, 0.04)
    with torch.no_grad():
        model.log_s.fill_(math.log(1e4))
        model.table_albedo.fill_(math.log(table.albedo))
        model.table_offset.fill_(table.height_m)
    b = model.make_batch(torch.arange(3), train=False)
    outside = (b.returns > 0) & (b.hit == 0)
    assert int(outside.sum()) > 0.05 * b.n_rays  # the case at hand: table rays outside the scene sphere
    got = model.render_histograms(range(3))
    sim = Simulator(ball, scene.sensor, SimSettings(rays_per_zone=4096), seed=0, table=table)
    cycles = scene.cycles.double().numpy()[:, None, None]
    want = sim.detection_probabilities(sim.expected_rates(scene.poses.double().numpy())) * cycles
    bg = scene.background.double().numpy()[..., None] * cycles
    ratio = (got - bg).sum(-1) / (want - bg).sum(-1)  # signal per zone, model / simulator
    np.testing.assert_allclose(ratio, 1.0, atol=0.05)


def test_overrides_a_preset_reads_are_taken():
    cfg = with_overrides(preset_config("paper"), {"dtype": "float64", "loss.kind": "nll"})
    assert (cfg.dtype, cfg.loss.kind) == ("float64", "nll")
    assert with_overrides(preset_config("fast"), {"early_stop": False}).early_stop is False
    assert with_overrides(preset_config("paper"), {"default_budget_s": 60}).default_budget_s == 60
    # A field that takes None:
    assert with_overrides(preset_config("fast"), {"field.floor_z": None}).field.floor_z is None
    assert with_overrides(preset_config("fast"), {"loss.smooth_weight": 0.1}).loss.smooth_weight == 0.1
    assert with_overrides(preset_config("paper"), {"loss.tv_weight": 0.1}).loss.tv_weight == 0.1


def test_the_registry_holds_every_preset_under_the_names_the_light_modules_use():
    assert tuple(PRESETS) == PRESET_NAMES
    for name, preset in PRESETS.items():
        config = preset.config()
        assert config.preset == name and preset.name == name
        assert config is not preset.config()  # a fresh copy each time
        json.dumps(config.to_dict())


def write_capture(path, sensor, hists, poses, *, frames_per_pose=1, reference=None, scene=None, rig=None):
    with CaptureWriter.create(path, sensor, scene=scene, rig=rig, frames_per_pose=frames_per_pose) as w:
        for i, (h, p) in enumerate(zip(hists, poses)):
            ref = None if reference is None else reference[i]
            w.append(Measurement(h, p, i // frames_per_pose, i % frames_per_pose, ref))
        w.finish("complete")
    return path


@pytest.mark.parametrize("table", [{"z": "low"}, {"normal": [0, 0, 0], "offset": 0.0}, "yes"])
def test_a_malformed_scene_table_is_a_one_line_error_naming_the_manifest(tmp_path, table):
    sensor = sensor_preset("tmf8820")
    poses = np.stack([look_at(np.array([0.3, 0.0, 0.2]), np.zeros(3))])
    hists = np.full((1, 9, 128), 100, np.uint32)
    hists[..., ::2] += 1  # no sensor gives every bin the same count: such a capture is refused before its table
    cap = write_capture(tmp_path / "c", sensor, hists, poses, scene={"table": table, "real": False})
    with pytest.raises(CaptureError) as info:
        load_scene(cap)
    assert str(info.value).startswith(f"{cap / 'scan.json'}: scene table ") and "\n" not in str(info.value)


def test_scene_loading_sums_frames_masks_bad_bins_and_bounds_the_scene(tmp_path):
    sensor = sensor_preset("tmf8820")
    target = np.array([0.0, 0.1, 0.05])
    poses = np.stack([look_at(target + d, target) for d in ([0.3, 0, 0.1], [0, -0.2, 0.25], [-0.1, 0.1, 0.3])])
    poses = np.repeat(poses, 2, axis=0)  # two frames per pose
    hists = np.full((6, 9, 128), 100, np.uint32)
    hists[..., ::2] += 1  # no sensor gives every bin the same count: such a histogram is left out (plausibility)
    hists[1, 2, 40] = 2 ** 24 - 1  # a saturated 24-bit counter in the second frame of pose 0
    cap = write_capture(tmp_path / "c", sensor, hists, poses, frames_per_pose=2,
                        scene={"table": {"z": 0.0}, "real": False})
    scene = load_scene(cap)
    assert scene.n_views == 3 and float(scene.counts[0, 0, 5]) == 200.0
    torch.testing.assert_close(scene.cycles, torch.full((3,), 2.0 * sensor.cycles))
    assert not scene.valid[0, 2, 40] and scene.valid[1, 2, 40]
    assert not scene.valid[..., 0].any()  # the TMF8820's bin 0 is ignored
    np.testing.assert_allclose(scene.center.numpy(), target, atol=1e-5)
    dist = np.linalg.norm(poses[:, :3, 3] - target, axis=1).min()
    assert scene.radius == pytest.approx(0.6 * dist, rel=1e-4)
    assert scene.table is not None and not scene.table.fitted and float(scene.box[0, 2]) >= -0.01 * scene.radius - 1e-6
    assert not scene.real and scene.background_source == "sensor model"


def test_scene_sphere_from_first_returns_holds_the_object_and_no_sensor(box_capture):
    scene = load_scene(box_capture)
    c, r = scene.center.double().numpy(), scene.radius
    assert np.linalg.norm(box_mesh().vertices - c, axis=1).max() < r
    assert np.linalg.norm(scene.poses[:, :3, 3].double().numpy() - c, axis=1).min() > r
    assert scene.table is None and not scene.real  # simulated: no table, no TV


def test_a_view_near_the_centre_that_keeps_the_scene_sphere_off_the_object_is_said(tmp_path, box_capture):
    """One view 2 mm above a 0.20 m ball caps the sphere (no sensor inside) to 38 mm: nothing beyond it can be
    reconstructed, by either preset, and a 5.6 cm blob came out with no word of it."""
    ball = builtin_scene("sphere")
    far = fibonacci_hemisphere(4, 0.5, target=(0, 0, 0.1), min_elevation_deg=10)[:3]
    poses = np.stack([look_at(np.array([0, 0, 0.202]), np.array([0, 0, 0.1]))] + list(far))
    cap = tmp_path / "touch"
    simulate_capture(ball, sensor_preset("lcspc-sim"), poses, cap, settings=SimSettings(rays_per_zone=256),
                     progress=False)
    note = load_scene(cap).bound_note
    assert note is not None and "of the first returns lie beyond it" in note and "mm to the scene's centre" in note
    assert load_scene(box_capture).bound_note is None


def test_the_table_top_the_low_views_meet_far_out_is_not_said_to_lie_beyond_the_scene_sphere(tmp_path, capsys):
    """A spiral from 0 degrees reaches down to the table top, whose returns come from 40 cm out: they are the
    table's, not the object's, and the bound that leaves them out cuts nothing (it was said of every such capture)."""
    cap = tmp_path / "ball"
    assert cli_main(["simulate", "builtin:sphere", "--sensor", "tmf8820", "--table", "--min-elevation", "0",
                     "--out", str(cap)]) == 0
    scene = load_scene(cap)
    assert scene.table is not None and scene.bound_note is None


def test_scene_sphere_holds_a_thin_tall_object_whose_top_only_the_views_above_see(tmp_path):
    # Views aimed at the middle of a coat rack return mostly from near it; its top returns in the few views above.
    rack = builtin_scene("coat-rack")
    poses = fibonacci_hemisphere(64, 0.5, target=(0, 0, 0))
    cap = tmp_path / "rack"
    simulate_capture(rack, sensor_preset("lcspc-sim"), poses, cap, settings=SimSettings(rays_per_zone=1024),
                     progress=False)
    scene = load_scene(cap)
    c, r = scene.center.double().numpy(), scene.radius
    assert np.linalg.norm(rack.vertices - c, axis=1).max() < r, "the top of the rack is inside the sphere"
    assert np.linalg.norm(scene.poses[:, :3, 3].double().numpy() - c, axis=1).min() > r


def test_measured_capture_takes_its_pulse_from_the_reference_and_estimates_background(tmp_path):
    sensor = sensor_preset("tmf8820")
    target = np.zeros(3)
    poses = np.stack([look_at([0.0, 0.0, 0.3], target), look_at([0.2, 0.0, 0.25], target)])
    rng = np.random.default_rng(0)
    hists = rng.poisson(150, (2, 9, 128)).astype(np.uint32)
    ref = rng.poisson(4, (2, 128)).astype(np.float64)
    ref[:, 12:20] += 2e5 * np.exp(-0.5 * ((np.arange(12, 20) - 14.27) / 0.8) ** 2)
    cap = write_capture(tmp_path / "real", sensor, hists, poses, reference=ref.astype(np.uint32))
    scene = load_scene(cap)
    assert scene.real and scene.pulse_source == "reference" and scene.background_source == "estimated"
    np.testing.assert_allclose(scene.background.numpy(), 150 / sensor.cycles, rtol=0.1)
    kernel, origin = scene.pulse(1)
    assert origin == KERNEL_BEFORE and kernel.sum() == pytest.approx(1.0)
    assert abs(int(np.argmax(kernel)) - origin) <= 1  # the pulse peaks within a bin of the arrival
    sim_cap = write_capture(tmp_path / "sim", sensor, hists, poses, reference=ref.astype(np.uint32),
                            rig={"kind": "simulated"})
    assert load_scene(sim_cap).pulse_source == "sensor model"
    assert scene.pulse_note is None and load_scene(sim_cap).pulse_note is None  # a simulated one wants none


@pytest.mark.parametrize("level", [0, 200])
def test_a_measured_capture_whose_reference_shows_no_pulse_says_it_took_the_sensor_models(tmp_path, level):
    """Reference histograms all zero or flat (a dark or saturated reference path): the fit takes the preset's pulse,
    and the run says so (its scene notes are report warnings), not only report.json's scene.pulse."""
    sensor = sensor_preset("tmf8820")
    target = np.zeros(3)
    poses = np.stack([look_at([0.0, 0.0, 0.3], target), look_at([0.2, 0.0, 0.25], target)])
    hists = np.random.default_rng(0).poisson(150, (2, 9, 128)).astype(np.uint32)
    cap = write_capture(tmp_path / "real", sensor, hists, poses, reference=np.full((2, 128), level, np.uint32))
    scene = load_scene(cap)
    assert scene.real and scene.pulse_source == "sensor model"
    assert "reference histograms show no clear pulse" in scene.pulse_note and "tmf8820" in scene.pulse_note


def test_daemon_capture_from_a_simulated_sensor_is_not_measured(tmp_path):
    # The daemon records its sensor backend, not rig.kind; a sim TMF8820 must not get the measured-data treatment
    # (a fitted table at the lowest returns, estimated background, the reference pulse).
    sensor = sensor_preset("tmf8820")
    target = np.zeros(3)
    poses = np.stack([look_at([0.0, 0.0, 0.3], target), look_at([0.2, 0.0, 0.25], target)])
    hists = np.random.default_rng(0).poisson(150, (2, 9, 128)).astype(np.uint32)
    ref = np.random.default_rng(1).poisson(4, (2, 128)).astype(np.float64)
    ref[:, 12:20] += 2e5 * np.exp(-0.5 * ((np.arange(12, 20) - 14.27) / 0.8) ** 2)
    ref = ref.astype(np.uint32)
    kinds = {}
    for backend in ("sim", "serial", "i2c"):
        cap = write_capture(tmp_path / backend, sensor, hists, poses, reference=ref,
                            rig={"arm": {"backend": "sim"}, "sensor": {"backend": backend, "preset": "tmf8820"},
                                 "writer": "spadscan-daemon"})
        scene = load_scene(cap)
        kinds[backend] = (scene.real, scene.table is not None, scene.pulse_source, scene.background_source)
    assert kinds["sim"] == (False, False, "sensor model", "sensor model")
    assert kinds["serial"] == kinds["i2c"] == (True, True, "reference", "estimated")


def test_table_scene_renders_and_meshes_only_the_object(tmp_path):
    sensor = sensor_preset("tmf8820")
    target = np.array([0.0, 0.0, 0.03])
    poses = np.stack([look_at(target + d, target) for d in ([0.0, 0.05, 0.3], [0.25, 0, 0.15], [-0.2, -0.1, 0.2])])
    hists = np.random.default_rng(0).poisson(150, (3, 9, 128)).astype(np.uint32)
    cap = write_capture(tmp_path / "t", sensor, hists, poses, scene={"table": True, "real": True})
    scene = load_scene(cap)
    model = make_paper_model(scene, small_paper(), "cpu", RunPlan(steps=2, budget_s=None))
    assert model.terms.table and model.terms.crosstalk and model.terms.tv
    out = model.step()
    assert np.isfinite(out["loss"]) and out["tv"] > 0
    assert "table_offset_m" in model.summary()
    mesh = model.extract_mesh(32)
    assert mesh.bounds[0, 2] >= model.summary()["table_offset_m"] - 0.01


def test_the_likelihood_term_is_per_bin_of_a_view_whichever_view_comes_first():
    """`loss.kind` nll divided the deviance by the first view's valid bins: a dropped frame (no valid bin) first in
    a batch divided it by 1, and that step's loss was a thousand times the next one's."""
    sensor = sensor_preset("lcspc-sim")
    fw = sensor_forward(sensor, oversample=1)
    lam = torch.full((2, 1, sensor.n_bins), 2e-4, dtype=torch.float64)
    lam[:, 0, 400:410] = 0.05
    cycles = torch.full((2,), 5000.0, dtype=torch.float64)
    counts = (fw.detections(lam) * 5000.0).round()
    counts[0] = 0.0
    valid = torch.ones_like(counts, dtype=torch.bool)
    valid[0] = False
    alone = float(fw.nll(lam[1:], counts[1:], cycles[1:], valid[1:])) / sensor.n_bins
    for order in ([0, 1], [1, 0]):
        got = float(hist_nll(fw, lam[order], counts[order], cycles[order], valid[order]))
        assert got == pytest.approx(alone, rel=1e-12)
