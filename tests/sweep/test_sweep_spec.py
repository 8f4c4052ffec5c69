"""Sweep files: what they may say, the one-line errors for what they may not, and the points they expand into."""

from __future__ import annotations

import shutil

import pytest

from spadscan.cli import main
from spadscan.protocol.errors import ConfigError, MeshError
from spadscan.sweep.plan import PRODUCT_AXIS, make_plan
from spadscan.sweep.scenes import scene_mesh
from spadscan.sweep.spec import load_spec

from sweep_helpers import write_tiny


def write(tmp_path, text: str, name: str = "s.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_defaults_are_the_datasets_base_condition(tmp_path):
    spec = load_spec(write(tmp_path, '[sweep]\nscenes = ["builtin:sphere"]\n'))
    base = spec.base
    assert (base["sensor"], base["views"], base["radius_m"], base["cycles"]) == ("lcspc-sim", 256, 0.5, 5000)
    assert base["bin_ps"] == pytest.approx(8.348, abs=1e-3)  # 1.2514 mm of one-way range
    assert base["fov_deg"] == pytest.approx(30.06) and base["ambient"] == pytest.approx(2.484e-4)
    assert spec.methods == ("fast", "reprojection", "space-carving")
    plan = make_plan(spec)
    assert [(e.axis, e.value) for e in plan.entries] == [("base", None)] and len(plan.points) == 1


@pytest.mark.parametrize("text, message", [
    ('[sweep]\nscenes = ["builtin:sphere"]\n[grdi]\nviews = [1]\n', "unknown table [grdi]"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nveiws = 3\n', "[base] has no key 'veiws'"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[grid]\nviews = [16, 0]\n', "views = 0 is out of range"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[grid]\npower = [1, inf]\n', "power = inf must be a finite number"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[grid]\nviews = [16, 16]\n', "lists a value twice"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[grid]\nsensor = ["tmf8820"]\n', "[grid] has no key 'sensor'"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nviews = true\n', "views = True must be a whole number"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[fast]\nset = { "field.resolutoin" = 3 }\n', "no field 'resolutoin'"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[paper]\nsteps = 3\n', "[paper] configures a preset that"),
    ('[sweep]\nscenes = ["builtin:sphere"]\nmode = "all"\n', "mode = 'all' is not one of"),
    ('[sweep]\nscenes = []\n', "scenes is empty"),
    ('[sweep]\nscenes = ["builtin:teapot"]\n', "unknown built-in scene 'teapot'"),
    ('[sweep]\nscenes = ["lcspc:bunny"]\n', "give its folder with --lcspc DIR"),
    ('[sweep]\nscenes = ["missing.obj"]\n', "no such mesh file"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nsensor = "tmf8820"\n[grid]\nbin_ps = [100]\n',
     "measured (tabulated) pulse"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nmin_elevation_deg = 60\nmax_elevation_deg = 30\n',
     "must be below max_elevation_deg"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nschedule = "rings"\nviews = 10\n',
     "views = 10 is not a multiple of rings = 4"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[base]\ncycles = 5\n[grid]\npower = [1e-30]\n', None),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nambient = 2\n', "ambient = 2 photons/bin/cycle is out of range"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[grid]\nbin_ps = [1e4]\n', "[grid] bin_ps = 10000: sensor model"),
    ('[sweep\n', "not valid TOML"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nsensor = "tmf8820"\n[grid]\nfov_deg = [170]\n',
     "[grid] fov_deg = 170: fov_deg: sensor 'tmf8820' has rectangular zones, whose field widens only to under 126.8"),
    ('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nschedule = "rings"\nviews = 64\nmax_elevation_deg = 90\n',
     "max_elevation_deg = 90 puts the top ring of schedule 'rings' at the zenith, where its 16 views are one"),
])
def test_a_bad_sweep_file_is_one_line_naming_the_key(tmp_path, text, message):
    path = write(tmp_path, text)
    if message is None:  # odd but valid: physics decides what becomes of it
        make_plan(load_spec(path))
        return
    with pytest.raises((ConfigError, MeshError)) as err:
        make_plan(load_spec(path))
    assert message in str(err.value) and "\n" not in str(err.value)


def test_the_cli_refuses_a_bad_file_in_one_line(tmp_path, capsys):
    path = write(tmp_path, '[sweep]\nscenes = ["builtin:sphere"]\n[grid]\nfov_deg = [10, 200]\n')
    assert main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("spadscan: error: ") and "fov_deg = 200 deg is out of range" in err
    assert err.count("\n") == 1 and not (tmp_path / "out").exists()
    assert main(["sweep", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "out")]) == 1
    assert "no such sweep file" in capsys.readouterr().err


@pytest.mark.parametrize("address", ["bogus", "tcp://127.0.0.1", "foo://head:8786", ""])
def test_the_cli_refuses_a_scheduler_that_is_no_address_in_one_line(tmp_path, capsys, address):
    path = write(tmp_path, '[sweep]\nscenes = ["builtin:sphere"]\n[grid]\nfov_deg = [10, 20]\n')
    assert main(["sweep", str(path), "--out", str(tmp_path / "out"), "--scheduler", address]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"spadscan: error: --scheduler {address!r} is not a Dask scheduler's address")
    assert err.count("\n") == 1 and not (tmp_path / "out").exists()


def test_points_are_shared_by_entries_and_their_ids_are_stable(tmp_path):
    spec = load_spec(write_tiny(tmp_path))
    plan = make_plan(spec)
    assert [(e.axis, e.value) for e in plan.entries] == [("views", 8), ("views", 12), ("power", 1.0),
                                                          ("power", 1e-7)]
    # views = 12 and power = 1 are both the base condition: one point runs both entries.
    assert plan.entries[1].point_id == plan.entries[2].point_id and len(plan.points) == 3
    again = make_plan(load_spec(write_tiny(tmp_path)))
    assert list(again.points) == list(plan.points) and again.fingerprint == plan.fingerprint


def test_a_grown_grid_keeps_ids_and_a_changed_base_changes_them(tmp_path):
    tiny = write_tiny(tmp_path).read_text()
    plan = make_plan(load_spec(write(tmp_path, tiny, "a.toml")))
    grown = make_plan(load_spec(write(tmp_path, tiny.replace("views = [8, 12]", "views = [8, 12, 24]"), "b.toml")))
    assert set(plan.points) < set(grown.points) and grown.fingerprint == plan.fingerprint
    rebased = make_plan(load_spec(write(tmp_path, tiny.replace("views = 12\n", "views = 16\n"), "c.toml")))
    assert rebased.fingerprint != plan.fingerprint
    # A point is its parameters: views = 8 and 12 at power 1 are the same points on either base, the rest are not.
    shared = set(rebased.points) & set(plan.points)
    assert {(plan.points[p].params["views"], plan.points[p].params["power"]) for p in shared} == {(8, 1.0),
                                                                                                 (12, 1.0)}
    fewer_steps = make_plan(load_spec(write(tmp_path, tiny.replace("steps = 20", "steps = 10"), "d.toml")))
    assert fewer_steps.fingerprint != plan.fingerprint and not set(fewer_steps.points) & set(plan.points)


def test_rings_keep_their_own_band_below_the_zenith(tmp_path):
    import numpy as np

    from spadscan.sweep.params import point_poses

    spec = load_spec(write(tmp_path, '[sweep]\nscenes = ["builtin:sphere"]\n[base]\nschedule = "rings"\nviews = 64\n'))
    assert (spec.base["min_elevation_deg"], spec.base["max_elevation_deg"]) == (10.0, 80.0)
    poses, _ = point_poses(spec.base)
    assert len(np.unique(poses[:, :3, 3].round(9), axis=0)) == 64  # every view from its own position
    fibonacci = load_spec(write(tmp_path, '[sweep]\nscenes = ["builtin:sphere"]\n', "f.toml"))
    assert fibonacci.base["max_elevation_deg"] == 90.0  # the dataset's spiral is left as it was


def test_a_point_id_changes_with_the_ambient_rate_it_simulates(tmp_path):
    """`ambient` is per bin at the base condition's bins: the same bins and ambient number on two bases are two
    simulations, and two ids."""
    grid = write(tmp_path, '[sweep]\nscenes = ["builtin:sphere"]\n[base]\nbin_ps = 8.35\nambient = 2.5e-4\n'
                           '[grid]\nbin_ps = [16.7]\n', "a.toml")
    base = write(tmp_path, '[sweep]\nscenes = ["builtin:sphere"]\n[base]\nbin_ps = 16.7\nambient = 2.5e-4\n', "b.toml")
    (a,), (b,) = make_plan(load_spec(grid)).points.values(), make_plan(load_spec(base)).points.values()
    assert a.params == b.params and a.id != b.id


def test_product_mode_runs_every_combination(tmp_path):
    tiny = write_tiny(tmp_path).read_text().replace("[sweep]\n", '[sweep]\nmode = "product"\n')
    plan = make_plan(load_spec(write(tmp_path, tiny, "p.toml")))
    assert len(plan.entries) == 4 and len(plan.points) == 4
    assert {e.axis for e in plan.entries} == {PRODUCT_AXIS}
    assert {(t.params["views"], t.params["power"]) for t in plan.points.values()} == {
        (8, 1.0), (8, 1e-7), (12, 1.0), (12, 1e-7)}


def test_a_mesh_scene_is_known_by_its_content(tmp_path):
    import trimesh

    mesh = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    mesh.export(tmp_path / "box.ply")
    text = '[sweep]\nscenes = ["box.ply"]\n'
    plan = make_plan(load_spec(write(tmp_path, text)))
    assert make_plan(load_spec(write(tmp_path, text, "again.toml"))).points.keys() == plan.points.keys()
    scene = next(iter(plan.points.values())).scene
    assert scene_mesh(scene)[0].faces.shape == mesh.faces.shape
    trimesh.creation.box(extents=(0.1, 0.1, 0.2)).export(tmp_path / "box.ply")  # another mesh, the same name
    assert make_plan(load_spec(write(tmp_path, text, "changed.toml"))).points.keys() != plan.points.keys()
    with pytest.raises(MeshError, match="differs from the one the sweep was planned with"):
        scene_mesh(scene)  # a worker never runs a point on another mesh than the one planned


def test_lcspc_scenes_are_found_under_the_dataset_folder(tmp_path):
    import trimesh

    root = tmp_path / "LCSPCData"
    (root / "simulated" / "bunny").mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=2, radius=0.1).export(root / "simulated" / "bunny" / "bunny.obj")
    path = write(tmp_path, '[sweep]\nscenes = ["lcspc:bunny"]\n')
    plan = make_plan(load_spec(path), root)
    moved = tmp_path / "elsewhere"
    shutil.copytree(root, moved)
    assert make_plan(load_spec(path), moved).points.keys() == plan.points.keys()
    with pytest.raises(ConfigError, match="is --lcspc .* the dataset's folder"):
        make_plan(load_spec(path), tmp_path)


@pytest.mark.parametrize("base, message", [
    ('sensor = "tmf8820"\nbin_ps = 33.4\n', "bin_ps: sensor 'tmf8820' has a measured (tabulated) pulse"),
    ('schedule = "spiral"\n', "schedule = 'spiral' is not one of"),
    ('min_elevation_deg = 60\nmax_elevation_deg = 30\n', "must be below max_elevation_deg"),
])
def test_a_bad_base_condition_is_blamed_on_base_not_on_the_first_grid_entry(tmp_path, base, message):
    path = write(tmp_path, f'[sweep]\nscenes = ["builtin:sphere"]\n[base]\n{base}[grid]\nviews = [8]\n')
    with pytest.raises(ConfigError) as err:
        make_plan(load_spec(path))
    text = str(err.value)
    assert f"{path}: [base] (the base condition): " in text and message in text, text
    assert "[grid]" not in text, text
