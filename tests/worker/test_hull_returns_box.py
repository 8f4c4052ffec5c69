"""The SDF grid's box holds the carved hull's cells that first returns land in, not the object's uncarved shadow
(fast/hull.returns_box)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.fast.hull import RETURN_MIN_VIEWS, RETURN_VIEWS_PER_HIT, returns_box
from spadscan.worker.recon.fast.problem import build_problem
from spadscan.worker.recon.forward import choose_terms
from spadscan.worker.recon.presets import preset_config
from spadscan.worker.recon.scene_data import load_scene

BALL_RADIUS_M = 0.1


def _looking_along_x(n: int, y0: float = 0.1) -> np.ndarray:
    """n poses at x = -0.1 m, z = 0.1 m, spread along y from y0 by 0.05 mm, each looking along +x."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
    poses[:, :3, 3] = [[-0.1, y0 + 5e-5 * k, 0.1] for k in range(n)]
    return poses


def test_the_hull_is_cut_to_the_box_round_the_cells_the_returns_land_in():
    occ = np.zeros((20, 20, 60), bool)  # (z, y, x), 1 cm cells from the origin
    occ[8:12, 8:12, 4:8] = True  # the object, whose front the returns land on at x = 4 cm
    occ[8:12, 8:12, 8:60] = True  # its shadow, joined to it, out to the box's wall
    dirs = np.array([[[0.0, 0.0, 1.0]]])
    poses = _looking_along_x(RETURN_MIN_VIEWS)
    onset = np.full((len(poses), 1), 0.14)
    cut = returns_box(occ, (0.0, 0.0, 0.0), 0.01, poses, dirs, onset, pad_m=0.03)
    # returns reach x = 4-6 cm (onset plus 2 cm): the box keeps those cells and 3 cells beyond
    assert cut[10, 10, 4:10].all() and not cut[:, :, 10:].any()
    assert cut.sum() == occ[:, :, :10].sum()


def test_cells_that_too_few_views_return_from_do_not_widen_the_box():
    occ = np.zeros((20, 20, 60), bool)
    occ[8:12, 8:12, 4:60] = True
    dirs = np.array([[[0.0, 0.0, 1.0]]])
    poses = _looking_along_x(RETURN_MIN_VIEWS * RETURN_VIEWS_PER_HIT)
    onset = np.full((len(poses), 1), 0.14)
    onset[-2:] = 0.44  # two views' returns land 30 cm deeper: noise, or a glancing edge
    cut = returns_box(occ, (0.0, 0.0, 0.0), 0.01, poses, dirs, onset, pad_m=0.0)
    assert cut[10, 10, 4:7].all() and not cut[:, :, 7:].any()
    # of a capture of few views, each view's nearest patch is its own: one view's returns count
    few = returns_box(occ, (0.0, 0.0, 0.0), 0.01, poses[-3:], dirs, onset[-3:], pad_m=0.0)
    assert np.flatnonzero(few.any(axis=(0, 1))).tolist() == list(range(4, 37))
    nothing = returns_box(occ, (0.0, 0.0, 0.0), 0.01, poses, dirs, np.full_like(onset, np.nan), pad_m=0.0)
    assert (nothing == occ).all()  # no return at all: nothing to cut to


@pytest.fixture(scope="module")
def ball_captures(tmp_path_factory):
    """A 20 cm white ball on the floor seen by 64 lcspc-sim views from 0.5 m, aimed at the floor under it and at its
    middle: {aim height (m): capture folder}."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=BALL_RADIUS_M)
    ball.apply_translation([0.0, 0.0, BALL_RADIUS_M])
    out = {}
    for aim in (0.0, BALL_RADIUS_M):
        path = tmp_path_factory.mktemp("ball") / f"aim-{aim}"
        simulate_capture(ball, sensor_preset("lcspc-sim"), fibonacci_hemisphere(64, 0.5, target=(0.0, 0.0, aim)),
                         path, settings=SimSettings(rays_per_zone=512), seed=0, progress=False)
        out[aim] = path
    return out


def _problem(capture, pad_m):
    config = with_overrides(preset_config("fast"), {"field.hull_returns_pad_m": pad_m, "field.hull_resolution": 64})
    scene = load_scene(capture)
    return build_problem(scene, config, "cpu", choose_terms(scene))


def test_views_aimed_at_the_middle_get_a_grid_round_the_object_not_round_its_shadow(ball_captures):
    whole = _problem(ball_captures[BALL_RADIUS_M], None)
    cut = _problem(ball_captures[BALL_RADIUS_M], 0.02)
    # the shadow left the whole hull's box over 3 times the ball's width; cut, it holds the ball and its margins
    assert float(np.max(whole.box[1] - whole.box[0])) > 0.55
    assert float(np.max(cut.box[1] - cut.box[0])) < 0.4
    assert cut.notes["hull_cut_to_returns"] > 0.5
    assert (cut.box[0] < [-BALL_RADIUS_M, -BALL_RADIUS_M, 0.0]).all()
    assert (cut.box[1] > [BALL_RADIUS_M, BALL_RADIUS_M, 2 * BALL_RADIUS_M]).all()


def test_views_aimed_at_the_floor_keep_their_whole_hull(ball_captures):
    cut = _problem(ball_captures[0.0], 0.02)
    whole = _problem(ball_captures[0.0], None)
    assert cut.notes["hull_cut_to_returns"] == 0.0
    np.testing.assert_array_equal(cut.box[0], whole.box[0])
    np.testing.assert_array_equal(cut.box[1], whole.box[1])


def test_the_pad_is_checked_and_null_keeps_the_whole_hull():
    from spadscan.protocol.errors import ConfigError

    for bad in (-0.01, 2.0, "2cm"):
        with pytest.raises(ConfigError, match=r"^field\.hull_returns_pad_m .* must be in \[0, 1\] metres "
                                              r"\(none: the whole hull\)$"):
            with_overrides(preset_config("fast"), {"field.hull_returns_pad_m": bad}).check()
    with_overrides(preset_config("fast"), {"field.hull_returns_pad_m": None}).check()
