"""Ranking candidate views from a live snapshot (worker/live/next_views.py): each measure prefers the views that
see what the model lacks, every score is finite, and the ranking reaches next_views.json as the daemon reads it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from spadscan.daemon.config import ScanConfig, scan_to_dict, scan_with
from spadscan.protocol.next_views import candidate_poses, read_next_views
from spadscan.protocol.schedules import fibonacci_hemisphere, look_at
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker.live import next_views
from spadscan.worker.live.field_trace import TracedField
from spadscan.worker.live.next_views import is_adaptive, rank_candidates, update_next_views
from spadscan.worker.live.snapshot import FieldSnapshot, GridSnapshot, LiveSnapshot

N, R, CENTRE = 48, 0.06, np.array([0.0, 0.0, 0.07])
ORIGIN = np.array([-0.1, -0.1, -0.02])
VOXEL = 0.2 / (N - 1)
BAND = {"radius_m": 0.5, "target": [0.0, 0.0, 0.0], "min_elevation_deg": 10.0, "max_elevation_deg": 80.0}


def grid(radius_of=lambda x, y, z: R) -> GridSnapshot:
    z, y, x = np.meshgrid(*(ORIGIN[::-1][i] + VOXEL * np.arange(N) for i in range(3)), indexing="ij")
    d = np.sqrt(x ** 2 + y ** 2 + (z - CENTRE[2]) ** 2)
    return GridSnapshot((d - radius_of(x, y, z)).astype(np.float32), ORIGIN, VOXEL)


def snapshot(fields, poses) -> LiveSnapshot:
    return LiveSnapshot([FieldSnapshot(g, k, len(poses)) for k, g in enumerate(fields)], fields[-1], poses,
                        sensor_preset("lcspc-sim"), 0.0)


@pytest.fixture(autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_tracing_finds_the_sphere():
    field = TracedField(grid())
    o = torch.tensor([[0.5, 0.0, 0.07], [0.5, 0.0, 0.5]])
    d = torch.tensor([[-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    hits = field.trace(o, d, 1.0)
    assert hits.hit.tolist() == [True, False]
    assert abs(float(hits.t[0]) - (0.5 - R)) < 0.5 * VOXEL
    np.testing.assert_allclose(hits.normal[0].numpy(), [1, 0, 0], atol=0.05)
    assert float(hits.t[1]) == 1.0  # the far limit: it never enters the box


def test_coverage_prefers_the_side_no_view_has_seen():
    cand = candidate_poses(BAND, 128)
    taken = fibonacci_hemisphere(64, 0.5, (0, 0, 0), 10, 80)
    taken = taken[taken[:, 0, 3] > 0.1]  # only views from +x
    scores = rank_candidates(snapshot([grid()], taken), cand, "coverage")
    assert np.all(np.isfinite(scores)) and np.all(scores >= 0)
    x = cand[:, 0, 3]
    assert scores[x < -0.1].mean() > 3 * scores[x > 0.1].mean()
    assert cand[np.argmax(scores), 0, 3] < 0


@pytest.mark.parametrize("measure", ["disagreement", "sensitivity"])
def test_ray_measures_prefer_where_the_snapshots_disagree(measure):
    cand = candidate_poses(BAND, 128)
    still = grid()
    # a cap on the -y side still grows: hidden from +y
    moving = grid(lambda x, y, z: R + 0.02 * np.clip(-y / np.sqrt(x ** 2 + y ** 2 + (z - CENTRE[2]) ** 2 + 1e-12)
                                                     - 0.6, 0, None))
    y = cand[:, 1, 3]
    for fields in ([still, still, moving], [still, moving]):  # two snapshots: the newest against the one before
        scores = rank_candidates(snapshot(fields, cand[:4]), cand, measure)
        assert np.all(np.isfinite(scores))
        assert scores[y < -0.2].mean() > 3 * scores[y > 0.2].mean()
    # one snapshot, or snapshots that agree: nothing to choose by
    assert not rank_candidates(snapshot([still, still], cand[:4]), cand, measure).any()


def test_nothing_to_see_scores_zero_and_bad_input_is_refused():
    empty = GridSnapshot(np.ones((N, N, N), np.float32), ORIGIN, VOXEL)
    cand = candidate_poses(BAND, 16)
    for measure in ("coverage", "disagreement", "sensitivity"):
        assert not rank_candidates(snapshot([empty, empty], cand[:2]), cand, measure).any()
    assert rank_candidates(snapshot([empty], cand[:2]), np.zeros((0, 4, 4))).shape == (0,)
    with pytest.raises(ValueError, match="measure 'best'"):
        rank_candidates(snapshot([empty], cand[:2]), cand, "best")
    with pytest.raises(ValueError, match=r"\(n, 4, 4\)"):
        rank_candidates(snapshot([empty], cand[:2]), cand[:, :3])


def test_the_ranking_reaches_next_views_json(tmp_path):
    scan = scan_with(ScanConfig(), {"schedule": "adaptive", "views": 32, "initial_views": 8})
    manifest = {"schedule": {**scan_to_dict(scan), "candidates": 64}}
    assert is_adaptive(manifest) and not is_adaptive({"schedule": scan_to_dict(ScanConfig())})
    assert update_next_views(tmp_path, manifest, None) is None
    taken = fibonacci_hemisphere(8, 0.5, (0, 0, 0), 10, 80)
    path = update_next_views(tmp_path, manifest, snapshot([grid()], taken))
    nv = read_next_views(tmp_path)
    assert path == tmp_path / "next_views.json" and nv.pose_count == 8 and nv.measure == "coverage"
    assert len(nv.poses) == 64 and np.all(np.diff(nv.scores) <= 0)
    cand = candidate_poses(manifest["schedule"])
    assert np.abs(nv.poses[:, None] - cand[None]).max(axis=(2, 3)).min(axis=1).max() < 1e-12  # the scan's own


def test_a_view_next_to_one_ranked_ahead_gives_way_to_an_equally_covering_far_one():
    # a step at x = 0 faces +x: the measure alone ranks both +x candidates, 3 degrees apart, above the -x one, and a
    # scan taking the top two would see the -x side with neither
    bulge = grid(lambda x, y, z: R - 0.01 * (x > 0))
    eye = lambda azim_deg: CENTRE + 0.5 * np.array([np.cos(np.radians(azim_deg)), np.sin(np.radians(azim_deg)), 0.3])
    near, next_to_it, far = (look_at(eye(a), CENTRE) for a in (0.0, 3.0, 180.0))
    cand = np.stack([near, next_to_it, far])
    snap = snapshot([bulge], np.zeros((0, 4, 4)))
    alone = rank_candidates(snap, cand, "coverage", spread=False)
    assert alone[0] >= alone[1] > alone[2] > 0
    spread = rank_candidates(snap, cand, "coverage")
    assert np.all(np.isfinite(spread))
    assert spread[0] > spread[2] > spread[1] > 0


def test_spread_keeps_rankings_away_from_the_views_taken():
    # views taken on +x only: the first places of the spread ranking go round the object, not back to +x
    cand = candidate_poses(BAND, 128)
    taken = fibonacci_hemisphere(64, 0.5, (0, 0, 0), 10, 80)
    taken = taken[taken[:, 0, 3] > 0.1]
    scores = rank_candidates(snapshot([grid()], taken), cand, "coverage")
    order = np.argsort(-scores, kind="stable")

    def pairwise_deg(k):
        top = cand[order[:k], :3, 3]
        axes = top / np.linalg.norm(top, axis=1, keepdims=True)
        return np.degrees(np.arccos(np.clip(axes @ axes.T, -1, 1)))[np.triu_indices(k, 1)]

    # the measure alone: 11 degrees between two of the top four, a median of 23 among the top eight
    assert pairwise_deg(4).min() > 15.0 and np.median(pairwise_deg(8)) > 40.0


def test_coverage_seeks_the_space_no_view_has_emptied():
    # the surface is seen all round; a lump of the hull on the -y side, outside the surface, no view has emptied
    taken = fibonacci_hemisphere(64, 0.5, (0, 0, 0), 10, 80)
    hz, hy, hx = np.meshgrid(*(ORIGIN[::-1][i] + VOXEL * np.arange(N) for i in range(3)), indexing="ij")
    lump = np.sqrt(hx ** 2 + (hy + 0.085) ** 2 + (hz - 0.07) ** 2) - 0.02
    sphere = grid()
    hull = GridSnapshot(np.minimum(sphere.sdf, lump).astype(np.float32), ORIGIN, VOXEL)
    snap = LiveSnapshot([FieldSnapshot(sphere, 0, len(taken))], hull, taken, sensor_preset("lcspc-sim"), 0.0)
    cand = candidate_poses(BAND, 256)
    scores = rank_candidates(snap, cand, "coverage", unseen_space=True)
    assert np.all(np.isfinite(scores))
    y = cand[:, 1, 3]
    assert scores[y < -0.2].mean() > 2 * scores[y > 0.2].mean()
    assert cand[np.argmax(scores), 1, 3] < 0


def test_disagreement_scores_the_surface_moving_not_the_grid_s_box_changing():
    """A refit carves a new hull and so a new box: rays that miss the object leave each snapshot's box at another
    distance, which is no disagreement about the surface. The same surface on a larger box (the same nodes) scores
    next to nothing against a surface moved out by 2 mm everywhere."""
    cand = candidate_poses(BAND, 64)
    still = grid()
    pad = 5
    z, y, x = np.meshgrid(*(ORIGIN[::-1][i] + VOXEL * np.arange(-pad, N + pad) for i in range(3)), indexing="ij")
    d = np.sqrt(x ** 2 + y ** 2 + (z - CENTRE[2]) ** 2) - R
    larger = GridSnapshot(d.astype(np.float32), ORIGIN - pad * VOXEL, VOXEL)
    moved = GridSnapshot(still.sdf - 0.002, ORIGIN, VOXEL)
    box_only = rank_candidates(snapshot([still, larger], cand[:4]), cand, "disagreement", spread=False)
    surface = rank_candidates(snapshot([still, moved], cand[:4]), cand, "disagreement", spread=False)
    assert surface.max() > 0
    assert box_only.max() < 0.05 * surface.max(), (box_only.max(), surface.max())


@pytest.mark.parametrize("taken_views", [1, 8, 24])
def test_the_greedy_picks_scores_fall_strictly_so_the_file_keeps_their_order(taken_views):
    """next_views.json lists candidates by score: two greedy picks of one score would be listed by candidate index,
    a later pick ahead of an earlier one. Every pick's score is its own."""
    cand = candidate_poses(BAND, 512)
    taken = fibonacci_hemisphere(taken_views, 0.5, (0, 0, 0), 10, 80)
    scores = rank_candidates(snapshot([grid()], taken), cand, "coverage")
    picked = scores[scores > 0]
    assert len(picked) > 16 and len(np.unique(picked)) == len(picked)


@pytest.mark.parametrize("measure", ["coverage", "disagreement"])
def test_the_candidates_past_the_greedy_picks_follow_in_the_order_the_next_pick_would_see(measure, monkeypatch):
    """Past SPREAD_PICKS the ranking keeps each candidate's spread score below the last pick: ranked as the next
    greedy pick would rank them (after the last pick's own effect), so the first of them is that pick."""
    cand = candidate_poses(BAND, 128)
    taken = fibonacci_hemisphere(4, 0.5, (0, 0, 0), 10, 80)
    snap = snapshot([grid(), grid(lambda x, y, z: R + 0.01 * (x > 0))], taken)
    monkeypatch.setattr(next_views, "SPREAD_PICKS", 6)
    short = rank_candidates(snap, cand, measure)
    monkeypatch.setattr(next_views, "SPREAD_PICKS", 7)
    longer = rank_candidates(snap, cand, measure)
    picks = np.argsort(-short)[:6]
    np.testing.assert_array_equal(picks, np.argsort(-longer)[:6])
    rest = np.delete(short, picks)
    assert 0 < rest.max() < short[picks].min() and (rest > 0).sum() > 64
    assert int(np.argsort(-short)[6]) == int(np.argsort(-longer)[6])  # the seventh pick leads the rest
