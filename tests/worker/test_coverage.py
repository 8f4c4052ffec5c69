"""How many views saw each part of a reconstructed surface (worker/coverage.py): exact shares on a box seen from
known directions, undersides left out of the shares (and counted for the picture), occlusion counted, each vertex
given its nearest sample's views, bad input refused in one line; coverage.png's legend counts what the report counts
(that test alone draws: where this machine cannot draw off screen it is skipped, saying why; the others need no
picture and run everywhere)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh

from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.schedules import fibonacci_hemisphere, look_at
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker import reconstruct
from spadscan.worker.coverage import (FEW_VIEWS, mesh_coverage, summarize, surface_views, vertex_views,
                                      views_per_point)

SENSOR = sensor_preset("lcspc-sim")  # one 15-degree cone: a 10 cm box at 0.5 m lies wholly in it


def box():
    return trimesh.creation.box(extents=(0.1, 0.1, 0.1)).apply_translation([0.0, 0.0, 0.05])


def from_azimuth_zero(elevations_deg, radius=0.5):
    """Views in the x-z plane on the +x side, looking at the box's centre."""
    eyes = [(radius * math.cos(math.radians(e)), 0.0, 0.05 + radius * math.sin(math.radians(e)))
            for e in elevations_deg]
    return np.stack([look_at(eye, (0.0, 0.0, 0.05)) for eye in eyes])


def test_a_box_seen_all_round_is_covered_and_its_underside_left_out():
    cov = mesh_coverage(box(), fibonacci_hemisphere(64, 0.5, target=(0, 0, 0.05), min_elevation_deg=10), SENSOR)
    assert cov.share_few == 0.0 and cov.share_unseen == 0.0 and cov.few_heights_m is None
    assert cov.median_views >= 10
    # The bottom face (a sixth of the area) is an underside: left out of the sample.
    assert cov.points == pytest.approx(5 / 6 * 10_000, rel=0.05)


def test_a_box_seen_from_one_side_only_has_its_far_sides_unseen():
    # Every view on the +x side in the x-z plane: the +x face and the top are seen by all five, the -x face and the
    # two y faces (edge-on) by none: three of the five faces that are not the underside.
    cov = mesh_coverage(box(), from_azimuth_zero([10, 25, 40, 55, 70]), SENSOR)
    assert cov.share_few == pytest.approx(0.6, abs=0.03)
    assert cov.share_unseen == pytest.approx(0.6, abs=0.03)
    lo, hi = cov.few_heights_m
    assert 0.0 <= lo < 0.03 and 0.07 < hi <= 0.1


def test_a_face_behind_another_is_not_seen():
    # Points on the +x face of a box 20 cm behind the first along the views' line of sight: they face the sensors
    # and lie in every view's cone, but the first box hides them; without it, every view sees them.
    far = box().apply_translation([-0.2, 0.0, 0.0])
    y, z = np.meshgrid(np.linspace(-0.03, 0.03, 5), np.linspace(0.02, 0.06, 5))
    points = np.stack([np.full(y.size, -0.15 + 1e-4), y.ravel(), z.ravel()], axis=1)
    normals = np.tile([1.0, 0.0, 0.0], (len(points), 1))
    poses = from_azimuth_zero([5, 10, 15], radius=0.45)
    hidden = views_per_point(trimesh.util.concatenate([box(), far]), points, normals, poses, SENSOR)
    alone = views_per_point(far, points, normals, poses, SENSOR)
    assert (hidden == 0).all() and (alone == 3).all()


def test_fewer_than_three_views_is_few():
    assert FEW_VIEWS == 3
    two = mesh_coverage(box(), from_azimuth_zero([20, 50]), SENSOR)
    three = mesh_coverage(box(), from_azimuth_zero([20, 40, 60]), SENSOR)
    assert two.share_few == pytest.approx(1.0) and two.share_unseen == pytest.approx(0.6, abs=0.03)
    assert three.share_few == pytest.approx(0.6, abs=0.03), "the +x face and the top: three views each"


@pytest.mark.parametrize("mesh, poses, what", [
    (trimesh.Trimesh(), fibonacci_hemisphere(4, 0.5), "no surface"),
    (box(), np.zeros((3, 3)), "poses must be finite"),
    (box(), np.full((2, 4, 4), np.nan), "poses must be finite"),
    (trimesh.Trimesh([[0, 0, 0], [0, 0.1, 0], [0.1, 0, 0]], [[0, 1, 2]]),  # one triangle facing down
     fibonacci_hemisphere(4, 0.5), "only undersides"),
])
def test_bad_input_is_refused_in_one_line(mesh, poses, what):
    with pytest.raises(SpadscanError, match=what) as info:
        mesh_coverage(mesh, poses, SENSOR)
    assert "\n" not in str(info.value)


def test_undersides_are_counted_for_the_picture_and_left_out_of_the_shares():
    # Seen all round from above: the bottom face (a sixth of the area) faces away from every view.
    samples = surface_views(box(), fibonacci_hemisphere(64, 0.5, target=(0, 0, 0.05), min_elevation_deg=10), SENSOR)
    assert len(samples.points) == 10_000
    assert samples.underside.mean() == pytest.approx(1 / 6, abs=0.02)
    assert (samples.counts[samples.underside] == 0).all() and (samples.counts[~samples.underside] >= 3).all()
    assert summarize(samples).share_unseen == 0.0, "the shares leave the underside out"


def test_each_vertex_takes_the_views_of_its_nearest_sample():
    # Views on the +x side only: the +x face's corners are seen by all five views, the -x face's by none.
    mesh = trimesh.creation.box(extents=(0.1, 0.1, 0.1)).subdivide().subdivide().apply_translation([0, 0, 0.05])
    samples = surface_views(mesh, from_azimuth_zero([10, 25, 40, 55, 70]), SENSOR)
    views = vertex_views(mesh, samples)
    x = mesh.vertices[:, 0]
    inner_x_face = (x > 0.0499) & (np.abs(mesh.vertices[:, 1]) < 0.04) & (mesh.vertices[:, 2] > 0.01)
    assert views.shape == (len(mesh.vertices),)
    assert (views[inner_x_face] == 5).all() and (views[x < -0.0499] == 0).all()


def test_the_coverage_picture_counts_what_the_report_counts(tmp_path, saved_legends, draws_off_screen):
    """coverage.png's legend and the report's coverage (its warning, report.json) give the same shares: both leave
    the undersides out. The legend counted them, and one page read 34 % seen by fewer than three views in the
    picture and 24 % in its warning."""
    scene = SimpleNamespace(poses=torch.as_tensor(from_azimuth_zero([10, 25, 40, 55, 70])), sensor=SENSOR)
    cov = reconstruct._coverage(tmp_path, box(), scene, print)
    *shares, underside = saved_legends[0]
    assert underside == "underside: not counted"  # drawn grey, as the shares leave it out
    unseen, few, _ = (float(text.split(": ")[1].rstrip("%")) / 100 for text in shares)
    assert unseen == pytest.approx(cov.share_unseen, abs=0.005)
    assert unseen + few == pytest.approx(cov.share_few, abs=0.01)
