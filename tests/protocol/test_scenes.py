"""Built-in scenes: closed solids on z = 0, the right size, and the features each promises (concavity, thin stem)."""

from __future__ import annotations

import numpy as np
import pytest

from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.scenes import BUILTIN_SCENES, builtin_scene, revolve_profile


@pytest.mark.parametrize("name", list(BUILTIN_SCENES))
def test_scene_is_a_closed_solid_standing_on_the_ground(name):
    mesh = builtin_scene(name)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert len(mesh.split(only_watertight=False)) == 1
    lo, hi = mesh.bounds
    assert abs(lo[2]) < 1e-9, "stands on z = 0"
    assert 0.15 - 1e-9 <= hi[2] <= 0.25
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, 0, atol=1e-6)  # centred on the z axis
    assert np.all(hi[:2] - lo[:2] < 0.25)
    # Normals point outward: a step along a face normal leaves the solid, a step against it enters.
    faces = np.random.default_rng(0).choice(len(mesh.faces), size=min(200, len(mesh.faces)), replace=False)
    centre, normal = mesh.triangles_center[faces], mesh.face_normals[faces]
    assert not mesh.contains(centre + 5e-4 * normal).any()
    assert mesh.contains(centre - 5e-4 * normal).mean() > 0.95  # ray-parity tests can miss at edges
    assert BUILTIN_SCENES[name] and "\n" not in BUILTIN_SCENES[name]


@pytest.mark.parametrize("name", list(BUILTIN_SCENES))
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
