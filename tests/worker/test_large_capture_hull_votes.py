"""The first returns of every view vote for the carved hull's pieces (fast/hull.object_hull): the votes of many views
at once, the same as a view at a time."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from spadscan.worker.recon.fast import hull
from spadscan.worker.recon.fast.hull import object_hull


def votes_a_view_at_a_time(occ, origin, voxel, poses, zone_dirs, onset_m, depths_m=(0.0, 0.01, 0.02, 0.04)):
    """(labels, votes (n + 1,)): the plain rule, one view, zone and depth at a time."""
    lab, n = ndimage.label(occ)
    dirs = np.einsum("vij,zdj->vzdi", poses[:, :3, :3], zone_dirs[:, :: max(1, zone_dirs.shape[1] // 64)])
    shape = np.array(occ.shape[::-1])
    votes = np.zeros(n + 1, np.int64)
    for v in range(len(poses)):
        hit = np.zeros(n + 1, bool)
        for z in np.flatnonzero(np.isfinite(onset_m[v])):
            for dep in depths_m:
                p = poses[v, :3, 3] + dirs[v, z] * (onset_m[v, z] + dep)
                i = np.round((p - np.asarray(origin, float)) / voxel).astype(np.int64)
                good = np.all((i >= 0) & (i < shape), axis=1)
                hit[lab[i[good, 2], i[good, 1], i[good, 0]]] = True
        hit[0] = False
        votes += hit
    return lab, votes


def scene(views: int, seed: int = 0):
    """Three blobs of hull (one large, two small) and views round them whose returns land on them at random."""
    rng = np.random.default_rng(seed)
    occ = np.zeros((20, 22, 24), bool)
    occ[4:14, 5:15, 6:16] = True
    occ[16:19, 2:4, 2:4] = True
    occ[2:4, 18:21, 20:23] = True
    voxel, origin = 0.01, np.array([-0.12, -0.11, -0.10])
    eyes = rng.normal(size=(views, 3))
    eyes = 0.4 * eyes / np.linalg.norm(eyes, axis=1, keepdims=True)
    poses = np.tile(np.eye(4), (views, 1, 1))
    for k, eye in enumerate(eyes):
        fwd = rng.uniform(-0.1, 0.1, 3) - eye
        fwd /= np.linalg.norm(fwd)
        side = np.cross(fwd, [0.0, 0.0, 1.0])
        side /= np.linalg.norm(side)
        poses[k, :3, :3] = np.stack([side, np.cross(fwd, side), fwd], axis=1)
        poses[k, :3, 3] = eye
    dirs = rng.normal(size=(3, 130, 3)) * [0.2, 0.2, 1.0]
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    dirs[..., 2] = np.abs(dirs[..., 2])
    onset = rng.uniform(0.25, 0.45, (views, 3))
    onset[rng.random((views, 3)) < 0.3] = np.nan  # nothing detected
    return occ, origin, voxel, poses, dirs, onset


def test_the_pieces_votes_are_those_of_a_view_at_a_time(monkeypatch):
    occ, origin, voxel, poses, dirs, onset = scene(700)
    lab, votes = votes_a_view_at_a_time(occ, origin, voxel, poses, dirs, onset)
    assert votes[1:].min() < 0.2 * votes.max() < votes[1:].max(), "a piece is dropped, one kept"
    calls = []
    real = hull._piece_votes

    def counting(lab, n, origin, voxel, poses, *rest):
        calls.append(len(poses))
        return real(lab, n, origin, voxel, poses, *rest)

    monkeypatch.setattr(hull, "_piece_votes", counting)
    kept = object_hull(occ, origin, voxel, poses, dirs, onset)
    assert np.array_equal(kept, (votes >= 0.2 * votes.max())[lab] & (lab > 0))
    # A few calls of many views each, not a loop over the views.
    assert calls == [hull.VOTE_VIEWS, hull.VOTE_VIEWS, 700 - 2 * hull.VOTE_VIEWS]
    for lo in (0, 256, 512):
        got = real(lab, lab.max(), origin, voxel, poses[lo: lo + 256], dirs[:, ::2],
                   onset[lo: lo + 256], np.isfinite(onset[lo: lo + 256]), (0.0, 0.01, 0.02, 0.04))
        assert np.array_equal(got, votes_a_view_at_a_time(occ, origin, voxel, poses[lo: lo + 256], dirs,
                                                           onset[lo: lo + 256])[1])
