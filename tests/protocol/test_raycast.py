"""Ray casting against meshes (protocol/raycast.py): first hits, ranged exactly, in memory-bounded chunks."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from spadscan.protocol import raycast
from spadscan.protocol.raycast import first_hits, make_intersector
from spadscan.protocol.sensor_presets import sensor_preset


def rays_at_a_sphere(n=50, seed=0):
    """A unit-radius sphere at the origin and n rays from (0, 0, 3) towards random points near it (some miss)."""
    rng = np.random.default_rng(seed)
    targets = rng.uniform(-1.4, 1.4, (n, 3)) * np.array([1, 1, 0])
    origins = np.tile([0.0, 0.0, 3.0], (n, 1))
    d = targets - origins
    return trimesh.creation.icosphere(subdivisions=3), origins, d / np.linalg.norm(d, axis=1, keepdims=True)


def test_first_hits_range_the_nearest_surface():
    mesh, o, d = rays_at_a_sphere()
    ray, rng_m, cos = first_hits(make_intersector(mesh), mesh, o, d)
    # Exact sphere: |o + t d| = 1 at t = -(o.d) - sqrt((o.d)^2 - |o|^2 + 1); the mesh is within ~1% of it.
    od = np.sum(o * d, axis=1)
    disc = od ** 2 - 9.0 + 1.0
    hit = disc > 0.05  # well inside the silhouette (the faceted edge may differ)
    assert set(np.flatnonzero(hit)) <= set(ray.tolist())
    exact = -od - np.sqrt(np.maximum(disc, 0))
    got = dict(zip(ray.tolist(), rng_m))
    for i in np.flatnonzero(hit):
        assert got[i] == pytest.approx(exact[i], abs=0.02)
    assert np.all((cos >= 0) & (cos <= 1))


def test_chunking_changes_nothing(monkeypatch):
    mesh, o, d = rays_at_a_sphere(n=40, seed=1)
    whole = first_hits(make_intersector(mesh), mesh, o, d)
    monkeypatch.setattr(raycast, "RAY_CHUNK", 7)  # 40 rays in 6 chunks, the last one short
    chunked = first_hits(make_intersector(mesh), mesh, o, d)
    order_w, order_c = np.argsort(whole[0]), np.argsort(chunked[0])
    for a, b in zip(whole, chunked):
        np.testing.assert_allclose(np.asarray(a)[order_w], np.asarray(b)[order_c])
    assert len(whole[0]) > 5  # the case has hits to compare


@pytest.mark.parametrize("rays_per_zone", [512, 767, 2000])
def test_every_zone_is_sampled_evenly_to_its_edges(rays_per_zone):
    """Zones whose grids round to more rays than the smallest keep an even spread of them: the first rays alone (the
    grid runs x-major) left a TMF8820 zone's last twentieth in x a third of its rays at 767 rays a zone (a patch
    there returned nothing)."""
    sensor = sensor_preset("tmf8820")
    rays = raycast.zone_rays(sensor.zones, rays_per_zone, seed=0)
    for zone, dirs in zip(sensor.zones, rays.directions):
        across = (dirs[:, 0] / dirs[:, 2] - zone.tan_x[0]) / (zone.tan_x[1] - zone.tan_x[0])
        assert 0.035 < (across > 0.95).mean() < 0.065, f"the zone's last twentieth in x at {rays_per_zone} rays"
