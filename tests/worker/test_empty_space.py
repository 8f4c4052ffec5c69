"""The empty-space bias of table scenes (worker/recon/fast/parts/empty_space.py), the thin sheets it leaves
(parts/thin_sheets.py) and the hidden-space fills of fits and meshes (grid_ops.py, mesh.py)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from spadscan.protocol.errors import ConfigError
from spadscan.protocol.sensor_model import Zone
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker.recon.fast.grid_ops import cavities, fill_under_overhangs, under_overhangs
from spadscan.worker.recon.fast.mesh import FLOATER_FRACTION, clean_solid
from spadscan.worker.recon.fast.parts.empty_space import (heard_bins, heard_view_bins, pressure_weight, push_to_empty,
                                                          view_coverage, views_hearing)
from spadscan.worker.recon.fast.parts.thin_sheets import thin_near_table

pytestmark = pytest.mark.usefixtures("one_thread")


def pose_at(position, rotation=np.eye(3)):
    p = np.eye(4)
    p[:3, :3], p[:3, 3] = rotation, position
    return p


# ---- coverage -------------------------------------------------------------------------------------------------------
def test_coverage_counts_the_views_whose_zones_hold_a_point():
    zones = sensor_preset("tmf8820").zones  # 3x3 rect zones, tan x in [-0.294, 0.294], tan y in [-0.291, 0.291]
    down = np.diag([1.0, -1.0, -1.0])  # boresight (+z of the sensor) pointing down the world's -z
    poses = torch.tensor(np.stack([pose_at([0, 0, 1.0], down), pose_at([5.0, 0, 1.0], down),
                                   pose_at([0, 0, -1.0], down)]))  # the last one is below the points: behind it
    pts = torch.tensor([[0.0, 0.0, 0.0],      # straight below the first sensor
                        [0.29, 0.0, 0.0],     # tan 0.29: inside the outer zones' edge
                        [0.30, 0.0, 0.0],     # tan 0.30: outside every zone
                        [5.0, 0.1, 0.0]], dtype=torch.float64)  # below the second sensor only
    cov = view_coverage(pts, poses, zones).numpy()
    np.testing.assert_allclose(cov, [1 / 3, 1 / 3, 0.0, 1 / 3])


def test_coverage_leaves_out_what_a_dropped_frame_did_not_see():
    """A view whose histograms hold no data looked at nothing: the coverage is the one without it; a zone of a view
    that holds none takes only that zone's field away."""
    zones = sensor_preset("tmf8820").zones
    down = np.diag([1.0, -1.0, -1.0])
    poses = torch.tensor(np.stack([pose_at([0, 0, 1.0], down), pose_at([0.05, 0, 1.0], down),
                                   pose_at([5.0, 0, 1.0], down)]))
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.25, 0.0, 0.0], [5.0, 0.1, 0.0]], dtype=torch.float64)
    looked = torch.ones((3, len(zones)), dtype=torch.bool)
    looked[1] = False  # the second view dropped whole
    np.testing.assert_allclose(view_coverage(pts, poses, zones, looked=looked).numpy(),
                               view_coverage(pts, poses[[0, 2]], zones).numpy())
    centre = [z for z, zone in enumerate(zones) if zone.holds(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))]
    looked = torch.ones((3, len(zones)), dtype=torch.bool)
    looked[0, centre] = False  # the first view's centre zone dropped: the point under it is seen by the second alone
    np.testing.assert_allclose(view_coverage(pts, poses, zones, looked=looked).numpy(), [1 / 3, 2 / 3, 1 / 3])


def test_coverage_of_a_cone_zone_and_shape_of_the_result():
    zones = (Zone(kind="cone", half_angle_rad=math.radians(15.0)),)
    poses = torch.tensor(np.stack([pose_at([0, 0, -1.0]), pose_at([0, 0, -1.0])]))  # looking up +z
    r_in, r_out = math.tan(math.radians(14.5)), math.tan(math.radians(15.5))
    pts = torch.tensor([[[r_in, 0, 0.0], [0, r_out, 0.0]], [[0, 0, 0.0], [0, 0, -2.0]]], dtype=torch.float64)
    cov = view_coverage(pts, poses, zones, chunk=3)  # chunks smaller than the points change nothing
    assert cov.shape == (2, 2)
    np.testing.assert_allclose(cov.numpy(), [[1.0, 0.0], [1.0, 0.0]])


# ---- heard ----------------------------------------------------------------------------------------------------------
def test_a_view_hears_a_point_in_its_zone_where_its_histogram_has_a_return_at_the_points_range():
    sensor = sensor_preset("lcspc-sim")  # one 15-degree cone
    poses = torch.tensor(np.stack([pose_at([0, 0, -0.5]), pose_at([0, 0, -0.5]), pose_at([0, 0, 0.5])]))
    loud = torch.zeros((3, 1, sensor.n_bins), dtype=torch.bool)
    loud[0, 0, int(sensor.bin_of_range(0.5))] = True  # a return from 0.5 m: the point's range from the first two
    loud[1, 0, int(sensor.bin_of_range(0.6))] = True  # a return 10 cm beyond it
    loud[2, 0, int(sensor.bin_of_range(0.5))] = True  # the third looks away (+z from above): the point is behind it
    pts = torch.tensor([[0.0, 0.0, 0.0],     # on every boresight, 0.5 m from each sensor
                        [0.2, 0.0, 0.0]],    # 22 degrees off the first two's boresight: outside their cone
                       dtype=torch.float64)
    heard = views_hearing(pts, poses, sensor, loud, half_width_m=0.005).numpy()
    np.testing.assert_array_equal(heard, [1, 0])
    wide = views_hearing(pts, poses, sensor, loud, half_width_m=0.11).numpy()  # a window reaching 0.6 m
    np.testing.assert_array_equal(wide, [2, 0])


def heard_one_by_one(points, poses, sensor, loud, half_width_m):
    """views_hearing's definition, point by point, view by view, zone by zone (the reference for the fast one)."""
    zero_bin, counts = sensor.bin_of_range(0.0), []
    for p in points.numpy():
        n = 0
        for v, pose in enumerate(poses.numpy()):
            rel = pose[:3, :3].T @ (p - pose[:3, 3])
            rng = float(np.linalg.norm(rel))
            lo = max(0, math.floor(zero_bin + (rng - half_width_m) / sensor.bin_width_m))
            hi = min(sensor.n_bins - 1, math.floor(zero_bin + (rng + half_width_m) / sensor.bin_width_m))
            n += any(bool(zone.holds(rel)) and lo <= hi and bool(loud[v, z, lo: hi + 1].any())
                     for z, zone in enumerate(sensor.zones))
        counts.append(n)
    return np.array(counts, float)


@pytest.mark.parametrize("zones", ["tmf8820", "overlapping"])
def test_views_hearing_counts_as_the_definition_does_point_by_point(zones):
    """The TMF8820's nine rect zones tile its view; the other sensor's zones overlap (a wide cone over a rect zone
    and a narrow cone inside it), so that a (point, view) lies in several and any of them may hear it."""
    sensor = sensor_preset("tmf8820")
    if zones == "overlapping":
        sensor = replace(sensor, zones=(Zone(kind="rect", tan_x=(-0.2, 0.1), tan_y=(-0.1, 0.2)),
                                        Zone(kind="cone", half_angle_rad=math.radians(14.0)),
                                        Zone(kind="cone", half_angle_rad=math.radians(5.0))))
    rng = np.random.default_rng(3)
    down = np.diag([1.0, -1.0, -1.0])
    poses = torch.tensor(np.stack([pose_at([x, y, 0.5], down) for x, y in rng.uniform(-0.05, 0.05, (5, 2))]))
    points = torch.tensor(rng.uniform([-0.12, -0.12, -0.1], [0.12, 0.12, 0.1], (300, 3)))
    loud = torch.as_tensor(rng.random((5, len(sensor.zones), sensor.n_bins)) < 0.08)
    expected = heard_one_by_one(points, poses, sensor, loud, 0.004)
    assert expected.min() == 0 and expected.max() >= 3  # some points heard by none, some by several
    got = views_hearing(points, poses, sensor, loud, half_width_m=0.004, chunk=64)
    np.testing.assert_array_equal(got.numpy(), expected)


def test_heard_bins_are_returns_over_the_threshold_and_never_the_unreliable_bins():
    sensor = sensor_preset("tmf8820")
    rng = np.random.default_rng(0)
    counts = rng.poisson(50.0, size=(1, sensor.n_zones, sensor.n_bins)).astype(float)
    peak = 60
    counts[0, 4, peak - 2: peak + 3] += [200, 2000, 8000, 2000, 200]
    loud = heard_bins(torch.as_tensor(counts), sensor, 5.0).numpy()
    assert loud[0, 4, peak] and not loud[0, 3, peak]
    for b in sensor.ignore_bins:
        assert loud[0, :, b].all()  # unreliable: never taken for silence


def test_a_view_of_several_frames_is_heard_with_its_own_cycles():
    """A view of 8 frames (counts summed, 8 frames' cycles) was read with one frame's cycles: its noise model ran
    out of cycles early and 3 bins in 4 counted as a return, so no node went unheard and the push never acted. Read
    with the view's cycles, the weak return alone is heard, as one frame of the same light is."""
    sensor = sensor_preset("lcspc-sim")
    rng = np.random.default_rng(0)
    rate = np.full(sensor.n_bins, sensor.background)  # photons a bin a cycle
    rate[300:304] += [0.002, 0.006, 0.004, 0.001]
    first = (1 - np.exp(-rate)) * np.exp(-np.concatenate([[0.0], np.cumsum(rate)[:-1]]))  # first photon per bin
    shares = np.append(first, 1 - first.sum())

    def frames(n):
        return sum(rng.multinomial(sensor.cycles, shares)[:-1] for _ in range(n)).astype(float)[None, None]

    eight = heard_view_bins(torch.as_tensor(frames(8)), torch.tensor([8.0 * sensor.cycles]), sensor, 5.0)[0, 0]
    heard = set(np.flatnonzero(eight.numpy())) - set(sensor.ignore_bins)
    assert heard and heard <= set(range(280, 320)), sorted(heard)  # the return, widened by the matched filter
    one = frames(1)
    np.testing.assert_array_equal(heard_view_bins(torch.as_tensor(one), torch.tensor([float(sensor.cycles)]), sensor,
                                                  5.0).numpy(), heard_bins(torch.as_tensor(one), sensor, 5.0).numpy())


def test_pressure_weight_falls_from_one_to_zero_with_coverage():
    w = pressure_weight(torch.tensor([0.0, 0.1, 0.2, 0.5, 1.0]), 0.2).numpy()
    np.testing.assert_allclose(w, [1.0, 0.5, 0.0, 0.0, 0.0])
    for bad in (0.0, -0.1, 1.5):
        with pytest.raises(ConfigError, match="pressure coverage"):
            pressure_weight(torch.zeros(3), bad)


# ---- the push -------------------------------------------------------------------------------------------------------
def test_push_acts_on_surface_nodes_only_by_a_fraction_of_the_gradient_rms():
    voxel = 0.01
    z = torch.arange(8, dtype=torch.float64)[:, None, None].expand(8, 3, 3)
    sdf = ((z - 3.5) * voxel)[None, None].clone()  # a plane between nodes 3 and 4: those two are surface nodes
    grad = torch.zeros_like(sdf)
    grad[0, 0, 3] = 3.0
    grad[0, 0, 4] = -4.0
    weight = torch.ones_like(sdf)
    weight[0, 0, :, 0, 0] = 0.0  # one column that many views look at: no push
    before = grad.clone()
    push_to_empty(grad, sdf, voxel, weight, 0.2)
    rms = math.sqrt((9 + 16) / 2)
    delta = (grad - before)[0, 0]
    assert float(delta[3, 1, 1]) == pytest.approx(-0.2 * rms) and float(delta[4, 2, 2]) == pytest.approx(-0.2 * rms)
    assert float(delta[3, 0, 0]) == 0.0 and float(delta[4, 0, 0]) == 0.0
    off_surface = torch.ones(8, dtype=torch.bool)
    off_surface[3:5] = False
    assert bool((delta[off_surface] == 0).all())


def test_push_leaves_a_gradient_alone_when_there_is_nothing_to_scale_by():
    sdf = torch.full((1, 1, 4, 4, 4), 0.5, dtype=torch.float64)  # no surface
    grad = torch.randn_like(sdf)
    before = grad.clone()
    push_to_empty(grad, sdf, 0.01, torch.ones_like(sdf), 0.2)
    assert torch.equal(grad, before)
    sdf[0, 0, 2] = 0.0  # a surface, but a zero data gradient on it (nothing seen yet)
    grad = torch.zeros_like(sdf)
    push_to_empty(grad, sdf, 0.01, torch.ones_like(sdf), 0.2)
    assert bool((grad == 0).all())


# ---- hidden space ---------------------------------------------------------------------------------------------------
def mushroom(n=12):
    """(values (nz, ny, nx), z (nz,)): a floor at z = 2 (nodes below it empty), a stem on it, a wide cap above a gap."""
    solid = np.zeros((n, n, n), bool)
    solid[2:8, 5:7, 5:7] = True   # stem, standing on the floor
    solid[8:10, 2:10, 2:10] = True  # cap: the space under it, beside the stem, is hidden from above
    return np.where(solid, -1.0, 1.0).astype(np.float32), np.arange(n, dtype=float)


def test_space_under_an_overhang_is_filled_down_to_the_table_only():
    values, z = mushroom()
    out = fill_under_overhangs(values, z, 2.0, -0.5)
    assert np.all(out[2:8, 2:10, 2:10] < 0)  # under the cap, down to the floor
    assert np.all(out[:2] == values[:2])  # under the table: untouched
    assert np.all(out[:, 0:2] > 0) and np.all(out[10:] > 0)  # beside and above the cap: still empty
    assert np.all(values[2:8, 2:5, 2:5] > 0)  # (the input is not changed)


def test_space_under_an_overhang_is_left_empty_where_a_wide_gap_opens_it_to_the_side():
    """A head on a post: the air round the post under the head is open to the side (views see into it), so it is
    no hidden space once gaps wider than 2 x 2 + 1 nodes count as open. A hollow under a roof whose only opening
    is a slot 3 nodes wide stays hidden, and is filled either way."""
    n = 40
    z = np.arange(n, dtype=float)
    solid = np.zeros((n, n, n), bool)
    solid[2:25, 18:22, 18:22] = True   # a post 4 nodes wide on the floor at z = 2
    solid[25:31, 12:28, 12:28] = True  # a head 16 nodes wide above it: 6 nodes of air under it on every side
    under = 23 * (16 * 16 - 4 * 4)
    assert under_overhangs(solid, z, 2.0)[2:25, 12:28, 12:28].sum() == under
    # Left filled: only the nodes in the corner between the post and the floor, which the opening rounds off.
    assert under_overhangs(solid, z, 2.0, open_nodes=2).sum() < 0.02 * under
    shell = np.zeros((n, n, n), bool)
    shell[2:20, 5:35, 5:35] = True
    shell[2:17, 8:32, 8:32] = False      # a hollow on the floor under a roof 3 nodes thick, walls 3 nodes thick
    shell[2:5, 8:11, 5:8] = False        # a slot 3 nodes wide through a wall at the foot
    hollow = under_overhangs(shell, z, 2.0)
    assert hollow[2:17, 8:32, 8:32].all()
    assert under_overhangs(shell, z, 2.0, open_nodes=2)[2:17, 8:32, 8:32].all(), "a narrow slot is no view into it"
    opened = under_overhangs(shell, z, 2.0, open_nodes=1)[2:17, 8:32, 8:32]
    assert opened.sum() < 0.05 * hollow[2:17, 8:32, 8:32].sum(), "a slot 3 nodes wide is open at 1"


def test_pockets_closed_by_the_floor_are_cavities_only_when_the_floor_is_given():
    n = 10
    solid = np.zeros((n, n, n), bool)
    solid[2:7, 2:8, 2:8] = True
    solid[2:5, 4:6, 4:6] = False  # a pocket open only downwards, onto the floor at node 2
    below = np.broadcast_to((np.arange(n) < 2)[:, None, None], solid.shape)
    assert not cavities(solid).any()
    cav = cavities(solid, below)
    assert cav.sum() == 3 * 2 * 2 and cav[2:5, 4:6, 4:6].all()
    values = np.where(solid, -1.0, 1.0).astype(np.float32)
    assert np.all(clean_solid(values, below_floor=below)[2:5, 4:6, 4:6] < 0)
    assert np.all(clean_solid(values)[2:5, 4:6, 4:6] > 0)


def test_pieces_much_smaller_than_the_object_are_removed_and_comparable_ones_kept():
    solid = np.zeros((30, 30, 30), bool)
    solid[2:22, 2:22, 2:22] = True  # the object: 8,000 nodes
    solid[2:4, 25:27, 25:27] = True  # 8 nodes: a floater (0.1%)
    solid[2:12, 25:29, 2:12] = True  # 400 nodes (5%): a second object
    assert 8 < FLOATER_FRACTION * 8000 < 400
    values = np.where(solid, -1.0, 1.0).astype(np.float32)
    assert np.array_equal(clean_solid(values) < 0, solid), "by default (no table) every piece stays"
    out = clean_solid(values, FLOATER_FRACTION)
    assert np.all(out[2:4, 25:27, 25:27] > 0)
    assert np.all(out[2:22, 2:22, 2:22] < 0) and np.all(out[2:12, 25:29, 2:12] < 0)
    assert np.all((out < 0) == (solid & ~np.pad(np.ones((2, 2, 2), bool), ((2, 26), (25, 3), (25, 3)))))


# ---- thin sheets just above the table -------------------------------------------------------------------------------
def table_block_and_curtain():
    """Node rows 1 cm apart from z = -0.03 m, the table at z = 0: a thick block on the table, a 2-node thick curtain
    beside it reaching 7 cm up, and a thin fin on the block's top, 8 cm above the table."""
    z = -0.03 + 0.01 * np.arange(14)
    solid = np.zeros((14, 20, 20), bool)
    solid[3:11, 4:12, 4:12] = True  # block from the table (row 3, z = 0) to z = 7 cm
    solid[3:10, 4:12, 14:16] = True  # curtain, separate from the block
    solid[11:13, 7:9, 4:12] = True  # fin on the block's top (z = 8-9 cm)
    return solid, z


def test_thin_sheets_within_the_band_above_the_table_are_emptied_and_thick_bodies_kept():
    solid, z = table_block_and_curtain()
    thin = thin_near_table(solid, z, 0.0, 0.04, 2)
    assert not (thin & ~solid).any()
    band = (z >= 0.0) & (z < 0.04)
    curtain = np.zeros_like(solid)
    curtain[3:10, 4:12, 14:16] = True
    assert thin[curtain & band[:, None, None]].all()  # the curtain goes within the band...
    assert not thin[curtain & ~band[:, None, None]].any()  # ...and stays above it
    assert not thin[11:13].any()  # the fin is above the band
    core = np.zeros_like(solid)
    core[3:7, 6:10, 6:10] = True
    assert not thin[core].any()  # the block's inside and its base on the table stay solid
    # At most the block's vertical edges are rounded: every node it loses lies within two steps of one.
    _, yy, xx = np.nonzero(thin[:, 4:12, 4:12])
    to_edge = np.min([np.abs(yy - cy) + np.abs(xx - cx) for cy in (0, 7) for cx in (0, 7)], axis=0)
    assert to_edge.max() <= 2


def test_no_thin_sheet_removal_without_a_band_or_a_radius():
    solid, z = table_block_and_curtain()
    assert not thin_near_table(solid, z, 0.0, 0.04, 0).any()
    assert not thin_near_table(solid, z, 0.5, 0.04, 2).any()  # the band lies above the grid
