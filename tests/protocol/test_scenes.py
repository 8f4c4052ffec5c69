"""Built-in scenes: closed solids on z = 0, the right size, and the features each promises (concavity, thin stem)."""

from __future__ import annotations

import numpy as np
import pytest

from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.scenes import (BUILTIN_SCENES, DATASET_SCENES, SPLITS, TABLE_SCENES, builtin_scene,
                                      revolve_profile, scene_listing, split_of)


HEIGHT_M = {"sphere": 0.20, "cup": 0.16, "lamp": 0.20, "pyramid": 0.15, "demo": 0.20, "teddy": 0.25, "head": 0.35,
            "duck": 0.15, "stool": 0.20, "mug": 0.15, "bowl": 0.11, "head-on-can": 0.50, "tall-block": 0.30,
            "bottle": 0.24, "mushroom": 0.18, "pawn": 0.20, "big-lamp": 0.35, "big-cup": 0.35, "big-goblet": 0.35,
            "tall-egg": 0.35, "chair": 0.26, "snowman": 0.28, "vase": 0.25, "ring-stand": 0.24, "cat": 0.23,
            "lighthouse": 0.34, "candlestick": 0.27, "kettle": 0.18, "pear": 0.20,
            "plant-stand": 0.18, "easel": 0.30, "coat-rack": 0.32, "side-table": 0.205, "dish": 0.06}
"""Each scene's height as its description gives it (metres, to the centimetre)."""

HOLES = {"mug": 1, "ring-stand": 1, "kettle": 1, "teddy": 2, "chair": 2, "easel": 2, "stool": 3, "plant-stand": 4}
"""The holes through each scene that has any (its genus: a handle, a ring, legs joined by rungs); the rest have none
(a vase's floor is closed, a cup's or a bowl's too)."""


@pytest.fixture(scope="module")
def meshes():
    """Every built-in scene, built once for the module's tests (each test gets a copy)."""
    built = {name: builtin_scene(name) for name in BUILTIN_SCENES}
    return lambda name: built[name].copy()


@pytest.mark.parametrize("name", list(BUILTIN_SCENES))
def test_scene_is_a_closed_solid_standing_on_the_ground(name, meshes):
    mesh = meshes(name)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert len(mesh.split(only_watertight=False)) == 1
    assert mesh.euler_number == 2 - 2 * HOLES.get(name, 0), "as many holes through it as its shape has"
    assert np.all(mesh.area_faces > 0), "no degenerate triangles"
    lo, hi = mesh.bounds
    assert lo[2] == 0.0, "stands on z = 0"
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, 0, atol=1e-6)  # centred on the z axis
    assert hi[2] == pytest.approx(HEIGHT_M[name], abs=0.0075), "as tall as its description says"
    if name in TABLE_SCENES:
        assert 0.30 - 1e-9 <= hi[2] <= 0.51 and np.all(hi[:2] - lo[:2] < 0.2), "tall and narrow"
    else:
        size = (hi - lo).max()
        assert 0.15 - 1e-9 <= size <= 0.35, f"the dataset's size (15-35 cm), got {size:.3f} m"
    # Normals point outward: a step along a face normal leaves the solid, a step against it enters.
    faces = np.random.default_rng(0).choice(len(mesh.faces), size=min(200, len(mesh.faces)), replace=False)
    centre, normal = mesh.triangles_center[faces], mesh.face_normals[faces]
    assert not mesh.contains(centre + 5e-4 * normal).any()
    assert mesh.contains(centre - 5e-4 * normal).mean() > 0.95  # ray-parity tests can miss at edges
    assert BUILTIN_SCENES[name] and "\n" not in BUILTIN_SCENES[name]


@pytest.mark.parametrize("name", ["sphere", "pyramid", "duck", "tall-block"])  # revolved, trimesh-made, meshed
def test_each_call_returns_a_fresh_mesh(name):
    a = builtin_scene(name)
    a.apply_translation([1, 0, 0])
    assert abs(builtin_scene(name).bounds[0, 2]) < 1e-9 and builtin_scene(name).bounds[1, 0] < 0.2


def _first_hit_z(mesh, x=0.0, y=0.0):
    """Height where a ray cast straight down at (x, y) first meets the surface."""
    locs, _, _ = mesh.ray.intersects_location([[x, y, 1.0]], [[0, 0, -1.0]])
    return locs[:, 2].max()


def _stem_radius(mesh, z):
    """Largest distance from the axis of the cross-section at height z (m)."""
    section = mesh.section(plane_origin=[0, 0, z], plane_normal=[0, 0, 1])
    return np.linalg.norm(section.vertices[:, :2], axis=1).max()


@pytest.mark.parametrize("name", ["cup", "demo"])
def test_concave_scenes_are_open_to_the_top(name):
    mesh = builtin_scene(name)
    top = mesh.bounds[1, 2]
    assert _first_hit_z(mesh) < top - 0.06  # looking down the axis you see the inside bottom, far below the rim


@pytest.mark.parametrize("name,z,low,high", [("lamp", 0.08, 0.005, 0.01), ("demo", 0.05, 0.005, 0.01)])
def test_thin_stems(name, z, low, high):
    r = _stem_radius(builtin_scene(name), z)
    assert low <= r <= high, f"stem radius {r * 1e3:.1f} mm"


def test_solid_scenes_are_closed_at_the_top():
    for name in ("sphere", "lamp", "pyramid"):
        mesh = builtin_scene(name)
        assert _first_hit_z(mesh) == pytest.approx(mesh.bounds[1, 2], abs=2e-3)


def test_unknown_scene_lists_the_names():
    with pytest.raises(SpadscanError) as info:
        builtin_scene("teapot")
    msg = str(info.value)
    assert "teapot" in msg and all(n in msg for n in BUILTIN_SCENES) and "\n" not in msg


def test_revolve_refuses_open_profiles():
    with pytest.raises(SpadscanError, match="profile"):
        revolve_profile(np.array([[0.01, 0], [0.05, 0], [0, 0.1]]))
    mesh = revolve_profile(np.array([[0, 0.1], [0.05, 0.05], [0, 0]]))  # walked the other way: still outward
    assert mesh.volume > 0 and mesh.is_watertight


# ---- the splits ----------------------------------------------------------------------------------------------------
def test_every_builtin_is_in_one_split_or_a_table_scene_and_the_splits_do_not_overlap():
    order = ("tuning", "validation", "holdout", "check")
    assert tuple(SPLITS) == order
    splits = [set(SPLITS[s]) for s in order]
    for i, a in enumerate(splits):
        assert all(not a & b for b in splits[i + 1:])
    tuning = ("sphere", "cup", "lamp", "pyramid", "demo", "big-lamp", "big-cup", "big-goblet", "tall-egg",
              "plant-stand", "side-table", "dish")
    assert splits[0] == {f"builtin:{n}" for n in tuning} | set(DATASET_SCENES)
    assert set(DATASET_SCENES) == {"lcspc:sphere", "lcspc:bunny", "lcspc:soap"}
    for name in BUILTIN_SCENES:
        homes = [f"builtin:{name}" in split for split in splits] + [name in TABLE_SCENES]
        assert sum(homes) == 1, name
        assert split_of(name) == (order[homes.index(True)] if any(homes[:4]) else None)
    everything = set().union(*splits)
    assert all(m.split(":", 1)[1] in BUILTIN_SCENES for m in everything if m.startswith("builtin:"))


def test_the_listing_names_every_scene_under_its_split():
    text = scene_listing()
    starts = [(text.index(title), split) for title, split in (("validation split", "validation"),
                                                              ("holdout split", "holdout"), ("check split", "check"),
                                                              ("tall objects", None))]
    for name in BUILTIN_SCENES:
        at = text.index(f"    {name} ")
        group = "tuning"
        for start, split in starts:
            if at > start:
                group = split
        assert group == split_of(name), name
    assert all(n.split(":")[1] in text[:starts[0][0]] for n in DATASET_SCENES)


# ---- what each new scene promises ------------------------------------------------------------------------------------
def _section_parts(mesh, z):
    """The closed outlines (k, 2) of the horizontal section at height z (m), x and y in metres."""
    section = mesh.section(plane_origin=[0, 0, z], plane_normal=[0, 0, 1])
    return [loop[:, :2] for loop in section.discrete]


def _area(loop):
    x, y = loop[:, 0], loop[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))


def _extent(loop):
    return loop.max(axis=0) - loop.min(axis=0)


def test_teddy_has_two_thin_ears_above_its_head(meshes):
    ears = _section_parts(meshes("teddy"), 0.240)
    assert len(ears) == 2
    for ear in ears:
        dx, dy = _extent(ear)
        assert 0.005 <= dy <= 0.016 and dx > dy, "thin, and broad across the head"
    gap = np.linalg.norm(ears[0][:, None] - ears[1][None], axis=-1).min()
    assert gap > 0.03, "standing apart"


def test_head_stands_on_a_square_plinth(meshes):
    mesh = meshes("head")
    (plinth,) = _section_parts(mesh, 0.03)
    dx, dy = _extent(plinth)
    assert dx == pytest.approx(0.14, abs=0.003) and dy == pytest.approx(0.14, abs=0.003)
    assert _area(plinth) == pytest.approx(dx * dy, rel=0.01), "square, not round"
    (neck,) = _section_parts(mesh, 0.12)
    assert _area(neck) < 0.3 * _area(plinth), "a neck on it, narrower"


def test_stool_legs_and_rungs_are_thin(meshes):
    mesh = meshes("stool")
    legs = _section_parts(mesh, 0.12)
    assert len(legs) == 3
    assert all(0.010 <= 2 * np.sqrt(_area(leg) / np.pi) <= 0.014 for leg in legs), "12 mm legs"
    assert mesh.euler_number < 2, "the rungs close loops between the legs"


def test_side_table_has_a_wide_top_over_four_thin_legs(meshes):
    mesh = meshes("side-table")
    legs = _section_parts(mesh, 0.10)
    assert len(legs) == 4
    assert all(0.010 <= 2 * np.sqrt(_area(leg) / np.pi) <= 0.014 for leg in legs), "12 mm legs"
    assert _first_hit_z(mesh, 0.0, 0.0) == pytest.approx(0.205, abs=2e-3)  # the top, solid over the middle
    under = mesh.ray.intersects_location([[0, 0, 0.05]], [[0, 0, 1.0]])[0]
    assert under[:, 2].min() == pytest.approx(0.190, abs=2e-3), "nothing under the top's middle but air"
    top = max(np.linalg.norm(loop, axis=1).max() for loop in _section_parts(mesh, 0.198))
    legs_top = max(np.linalg.norm(loop, axis=1).max() for loop in _section_parts(mesh, 0.17))
    assert top == pytest.approx(0.100, abs=2e-3) and top - legs_top > 0.025, "the top overhangs the legs"


@pytest.mark.parametrize("name, depth", [("mug", 0.12), ("bowl", 0.08), ("dish", 0.045)])
def test_mug_and_bowl_are_open_to_the_top(name, depth, meshes):
    mesh = meshes(name)
    assert _first_hit_z(mesh) < mesh.bounds[1, 2] - depth


def test_mug_handle_has_a_hole_through_it(meshes):
    mesh = meshes("mug")
    assert mesh.euler_number == 0, "one hole: the handle's"


def test_head_on_can_is_a_head_on_a_cylinder(meshes):
    mesh = meshes("head-on-can")
    (can,) = _section_parts(mesh, 0.10)
    assert 2 * np.sqrt(_area(can) / np.pi) == pytest.approx(0.12, abs=0.002)
    (skull,) = _section_parts(mesh, 0.40)
    assert _area(skull) > 1.5 * _area(can)


def _diameter(mesh, z):
    (loop,) = _section_parts(mesh, z)
    return 2 * np.sqrt(_area(loop) / np.pi)


def test_bottle_is_a_closed_round_body_under_a_narrow_neck(meshes):
    mesh = meshes("bottle")
    assert _diameter(mesh, 0.09) == pytest.approx(0.15, abs=0.003)
    assert _diameter(mesh, 0.215) == pytest.approx(0.04, abs=0.002)
    assert _first_hit_z(mesh) == pytest.approx(0.24, abs=0.001), "closed on top"


def test_mushroom_cap_overhangs_its_stem(meshes):
    mesh = meshes("mushroom")
    assert _diameter(mesh, 0.08) == pytest.approx(0.044, abs=0.002)
    assert _diameter(mesh, 0.13) > 3.5 * _diameter(mesh, 0.08)


def test_pawn_has_a_waist_under_a_collar_and_a_ball_head(meshes):
    mesh = meshes("pawn")
    base, waist, collar, head = (_diameter(mesh, z) for z in (0.007, 0.11, 0.124, 0.168))
    assert base == pytest.approx(0.11, abs=0.002) and head == pytest.approx(0.064, abs=0.002)
    assert waist < 0.6 * collar and waist < 0.7 * head


# ---- meshing a signed distance function ------------------------------------------------------------------------------
def test_a_meshed_sphere_and_box_lie_on_the_true_surface_to_well_under_a_millimetre():
    from spadscan.protocol import sdf
    from spadscan.protocol.sdf_mesh import mesh_sdf

    ball = mesh_sdf(sdf.sphere((0, 0, 0.05), 0.06), 0.08, 0.12, 0.002)
    r = np.linalg.norm(ball.vertices - [0, 0, 0.05], axis=1)
    floor = ball.vertices[:, 2] == 0
    smooth = ball.vertices[:, 2] > 0.004  # two voxels above the crease where the floor cuts the ball
    assert np.abs(r[smooth] - 0.06).max() < 0.03e-3  # marching cubes on a 6 cm ball at 2 mm: ~10 um
    assert np.abs(r[~floor] - 0.06).max() < 0.3e-3  # at the crease, a fraction of a voxel
    assert floor.any() and ball.bounds[0, 2] == 0.0, "cut flat at z = 0"
    assert ball.is_watertight and ball.volume == pytest.approx(
        np.pi / 3 * (0.11 ** 2) * (3 * 0.06 - 0.11), rel=2e-3)  # the cap above z = 0 of a ball of radius 6 cm
    block = mesh_sdf(sdf.box((0, 0, 0.05), (0.03, 0.02, 0.05)), 0.05, 0.12, 0.002)
    np.testing.assert_allclose(block.bounds, [[-0.03, -0.02, 0], [0.03, 0.02, 0.1]], atol=1e-6)


@pytest.mark.parametrize("name", ["teddy", "head", "duck", "stool", "mug", "bowl", "head-on-can"])
def test_the_sparse_grid_agrees_with_evaluating_every_node(name):
    """The coarse-to-fine evaluation skips nodes far from the surface: every sign must still be right and every node
    near the surface exact, at any grid (here a coarser one, to keep the dense evaluation cheap)."""
    from spadscan.protocol.scene_shapes import SOLID_SCENES
    from spadscan.protocol.sdf_mesh import grid_values

    scene = SOLID_SCENES[name]()
    voxel = 0.004
    xs = (np.arange(-int(scene.half_xy / voxel) - 2, int(scene.half_xy / voxel) + 2) + 0.5) * voxel
    zs = (np.arange(-2, int(scene.height / voxel) + 2) + 0.5) * voxel
    sparse = grid_values(scene.shape, xs, xs, zs, voxel)
    f32 = [a.astype(np.float32) for a in (xs, zs)]
    dense = scene.shape(f32[0][:, None, None], f32[0][None, :, None], f32[1][None, None, :])
    assert np.array_equal(sparse < 0, dense < 0)
    near = np.abs(dense) < 2 * voxel * np.sqrt(3)
    np.testing.assert_array_equal(sparse[near], dense[near])
    assert np.all(np.abs(sparse) <= np.abs(dense) + 1e-7), "elsewhere a bound, never more than the truth"
    assert near.mean() < 0.5, "and most nodes were skipped"


def test_a_solid_that_reaches_the_meshing_box_or_holds_nothing_is_a_one_line_error():
    from spadscan.protocol import sdf
    from spadscan.protocol.sdf_mesh import mesh_sdf

    with pytest.raises(SpadscanError, match="reaches the meshing box"):
        mesh_sdf(sdf.sphere((0, 0, 0.05), 0.06), 0.04, 0.12, 0.002)
    with pytest.raises(SpadscanError, match="no solid"):
        mesh_sdf(sdf.sphere((0, 0, -0.5), 0.06), 0.04, 0.12, 0.002)


@pytest.mark.parametrize("name", list(BUILTIN_SCENES))
def test_no_scene_is_scored_as_an_object_on_a_table_slab(name, meshes):
    """The metrics cut a ground truth above its largest flat upward level when that holds over a quarter of its area
    (a table slab, as in the dataset's real pyramid): a built-in's own flat top must stay well under that."""
    from spadscan.worker.ground_truth import table_top_z

    assert table_top_z(meshes(name)) is None


def test_the_pyramid_says_its_own_size_and_not_the_real_ones(meshes):
    """It was described as "like the dataset's real scene", which is 0.16 m square and 0.22 m tall: a stand-in of
    another shape. Its description gives its own base and height, and says it is smaller and lower."""
    text = BUILTIN_SCENES["pyramid"]
    assert text.startswith("a 0.15 m square, 0.15 m tall pyramid") and "smaller and lower" in text
    assert "like the dataset's real scene" not in text
    np.testing.assert_allclose(meshes("pyramid").extents, [0.15, 0.15, 0.15], atol=1e-9)
