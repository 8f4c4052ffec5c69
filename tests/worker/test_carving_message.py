"""The fast preset's error when space carving leaves nothing: it names the cause the first returns point to.

Returns that lie in the scene box and above the floor mean a thin or faint object that the views which missed its
return carved away (the carving thresholds are what to lower); returns outside the box or under the floor mean the
box or the floor is wrong.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from spadscan.protocol.errors import ConfigError
from spadscan.worker.carving.returns import below_default_level
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.errors import ReconstructionError
from spadscan.worker.recon.fast import problem
from spadscan.worker.recon.fast.model import make_fast_model
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.presets import preset_config
from spadscan.worker.recon.scene_data import load_scene
from worker_helpers import FAST_SMALL


pytestmark = pytest.mark.usefixtures("one_thread")

BOX = SimpleNamespace(voxel_m=np.full(3, 0.002), bounds_min=np.array([-0.05, -0.05, -0.05]),
                      bounds_max=np.array([0.05, 0.05, 0.05]))
"""A carving result's box as `_nothing_left` reads it: 10 cm across, 2 mm cells."""

ROD = np.stack([np.zeros(40), np.zeros(40), np.linspace(0.0, 0.04, 40)], axis=1)
"""First-return points along a thin upright rod standing on the floor z = 0, all inside BOX."""


def test_returns_inside_the_box_name_a_thin_object_and_the_thresholds_to_lower():
    msg = problem._nothing_left(ROD, BOX, 0.0, 5.0, 4.0)
    assert "\n" not in msg
    assert "40 histograms show a return, 40 of them in the scene box" in msg
    assert "thin or faint" in msg
    assert "field.carve_threshold = 5 and field.carve_weak_threshold = 4 noise deviations" in msg
    assert "--set field.carve_threshold=3 --set field.carve_weak_threshold=2" in msg
    assert "scene.radius" not in msg


def test_returns_outside_the_box_keep_the_box_advice():
    msg = problem._nothing_left(ROD + [0.2, 0.0, 0.0], BOX, 0.0, 5.0, 4.0)
    assert "\n" not in msg
    assert "only 0 of them in the scene box" in msg
    assert "check the capture's scene.radius and scene.center, or field.floor_z" in msg
    assert "thin or faint" not in msg


def test_cells_larger_than_the_returns_spread_name_the_scene_radius():
    """A scene radius of 50 m: 2 m cells, in which the returns of a 4 cm rod all lie, thresholds or not."""
    huge = SimpleNamespace(voxel_m=np.full(3, 2.0), bounds_min=np.full(3, -50.0), bounds_max=np.full(3, 50.0))
    msg = problem._nothing_left(ROD, huge, 0.0, 5.0, 4.0)
    assert "\n" not in msg
    assert "has 2000 mm cells, larger than the 40 mm the returns spread over" in msg
    assert "check the capture's scene.radius and scene.center" in msg
    assert "thin or faint" not in msg


def test_a_single_return_is_no_spread_to_blame_the_cells_on():
    """One return spreads over 0 mm: every cell is larger, and a return well inside a sensible box blamed the scene
    radius."""
    msg = problem._nothing_left(ROD[20:21], BOX, 0.0, 5.0, 4.0)
    assert "1 histogram shows a return, 1 of them in the scene box" in msg and "thin or faint" in msg, msg
    assert "mm cells, larger than" not in msg, msg


def test_returns_under_the_floor_keep_the_floor_advice():
    msg = problem._nothing_left(ROD, BOX, 0.045, 5.0, 4.0)
    assert "the floor (z = 0.045 m)" in msg and "field.floor_z" in msg
    assert "thin or faint" not in msg


def test_a_few_returns_beyond_the_box_still_point_to_a_thin_object():
    # A rod taller than the box: most of its returns in the box, its top's beyond (the box is not what failed).
    points = np.concatenate([ROD, ROD[:10] + [0.0, 0.0, 0.1]])
    msg = problem._nothing_left(points, BOX, 0.0, 5.0, 4.0)
    assert "50 histograms show a return, 40 of them" in msg and "thin or faint" in msg


def test_on_a_table_only_the_threshold_in_effect_is_named():
    msg = problem._nothing_left(ROD, BOX, 0.0, 5.0, None)
    assert ("field.carve_threshold = 5 noise deviations: run `spadscan reconstruct` on the capture with --set "
            "field.carve_threshold=3 --set field.carve_weak_threshold=3;") in msg, msg
    # Lower thresholds may fit noise: the run says so at its end, and then only a better capture helps.
    assert "says 'faint returns' at its end" in msg and msg.endswith(f"{problem.RESCAN})"), msg


def test_thresholds_below_their_defaults_already_are_not_offered_lower_but_a_new_scan():
    # A 6 mm wand refitted at 3 and 2 was carved away again; offered 2 and 1, it fitted noise (37.6 mm).
    msg = problem._nothing_left(ROD, BOX, 0.0, 3.0, 2.0, lowered=True)
    assert "thin or faint" in msg and "--set" not in msg, msg
    assert ("field.carve_threshold = 3 and field.carve_weak_threshold = 2 noise deviations put carving's level "
            "below its default already") in msg
    assert msg.endswith(f"{problem.RESCAN})"), msg


def test_thresholds_already_low_are_not_lowered_further():
    assert problem._lower_thresholds(3.0, 3.0) == (2.0, 1.0)
    assert problem._lower_thresholds(1.5, 1.0) is None
    msg = problem._nothing_left(ROD, BOX, 0.0, 2.0, 1.0)
    assert "as low as they go" in msg and "--set" not in msg


def test_no_return_at_all_says_so():
    msg = problem._nothing_left(np.zeros((0, 3)), BOX, 0.0, 5.0, 4.0)
    assert msg.startswith("space carving removed everything: no histogram shows a return above the threshold (5 ")


def test_return_points_lie_at_the_onset_along_the_zone_from_the_view():
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]  # looking down -z
    pose[:3, 3] = [0.1, 0.0, 0.5]
    dirs = np.array([[[0.1, 0.0, 1.0], [-0.1, 0.0, 1.0]], [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]])
    dirs /= np.linalg.norm(dirs, axis=2, keepdims=True)
    onset = np.array([[0.3, np.nan]])
    points = problem._return_points(onset, pose[None], dirs, np.ones((2, 2)))
    np.testing.assert_allclose(points, [[0.1, 0.0, 0.2]], atol=1e-12)


def _build(capture, overrides):
    config = with_overrides(preset_config("fast"), {**FAST_SMALL, **overrides})
    return make_fast_model(load_scene(capture), config, "cpu", RunPlan(steps=1, budget_s=None, seed=0))


def test_a_floor_above_the_object_is_named_when_the_fit_starts(cylinder_capture):
    with pytest.raises(ReconstructionError, match=r"only 0 of them in the scene box .* field\.floor_z\)$"):
        _build(cylinder_capture, {"field.floor_z": 0.3})


def test_an_object_carved_away_inside_its_box_names_the_thresholds_when_the_fit_starts(cylinder_capture,
                                                                                        monkeypatch):
    # The cylinder's returns lie in its box; its carved hull is taken away, as views that missed a thin part do.
    monkeypatch.setattr(problem, "object_hull", lambda occ, *a, **k: np.zeros_like(occ, bool))
    with pytest.raises(ReconstructionError, match="thin or faint") as err:
        _build(cylinder_capture, {"field.carve_threshold": 6.0, "field.carve_weak_threshold": 4.5})
    assert "--set field.carve_threshold=4 --set field.carve_weak_threshold=2.5" in str(err.value)
    with pytest.raises(ReconstructionError, match="thin or faint") as err:  # as that advice was followed
        _build(cylinder_capture, {"field.carve_threshold": 4.0, "field.carve_weak_threshold": 2.5})
    assert "below its default already" in str(err.value) and "--set" not in str(err.value)


def test_the_carving_error_and_the_end_of_run_check_agree_on_what_is_lowered(cylinder_capture, monkeypatch):
    """One rule (`returns.below_default_level`): thresholds are lowered where carving's level (the lower one in
    effect) lies below the defaults' (4 off a table). The carving threshold lowered alone to 4.5 leaves the level at
    4: the carving error offers lower ones, and the end of the run judges nothing at the default level; the weak
    one lowered to 3.5 lowers the level: no lower ones offered, and the end of the run judges at 4 too."""
    from spadscan.worker.reconstruct import _as_carving_reads, _signal

    monkeypatch.setattr(problem, "object_hull", lambda occ, *a, **k: np.zeros_like(occ, bool))
    scene = load_scene(cylinder_capture)
    cases = [({"field.carve_threshold": 4.5}, True, None), ({"field.carve_weak_threshold": 3.5}, False, 4.0)]
    for overrides, offers_lower, default_level in cases:
        with pytest.raises(ReconstructionError, match="thin or faint") as err:
            _build(cylinder_capture, overrides)
        msg = str(err.value)
        judged = _signal(scene, with_overrides(preset_config("fast"), {**FAST_SMALL, **overrides}),
                         _as_carving_reads(scene))
        assert ("--set field.carve_threshold=" in msg, judged.default_threshold) == (offers_lower, default_level), msg
        if offers_lower:
            assert "--set field.carve_threshold=2.5 --set field.carve_weak_threshold=2" in msg, msg
        else:
            assert "put carving's level below its default already" in msg, msg


def test_lowered_means_carving_s_level_below_the_defaults_level():
    """Off a table (weak threshold in effect, default 5 and 4) and on one (weak threshold None: the level is the
    carving threshold's, capped at 5)."""
    assert not below_default_level(4.5, 4.0, 5.0, 4.0)  # the carving threshold alone, above the level
    assert below_default_level(5.0, 3.5, 5.0, 4.0) and below_default_level(3.5, 3.5, 5.0, 4.0)
    assert not below_default_level(6.0, 4.5, 5.0, 4.0)  # raised
    assert below_default_level(4.5, None, 5.0, None) and not below_default_level(6.0, None, 5.0, None)


def test_the_hull_piece_vote_has_its_own_key(cylinder_capture):
    """`field.hull_min_votes` drops the carved pieces few first returns land in (the box's skirt, specks); 0 keeps
    every piece, a share over 1 is refused naming the key."""
    scene = load_scene(cylinder_capture)

    def hull_voxels(**overrides):
        config = with_overrides(preset_config("fast"), {**FAST_SMALL, **overrides})
        model = make_fast_model(scene, config, "cpu", RunPlan(steps=1, budget_s=None, seed=0))
        return model.problem.notes["hull_occupied_voxels"]

    assert hull_voxels() < hull_voxels(**{"field.hull_min_votes": 0.0})
    with pytest.raises(ConfigError, match=r"^field\.hull_min_votes 1\.5 must be in \[0, 1\] of the best piece's "
                                          r"votes \(0: every piece stays\)$"):
        hull_voxels(**{"field.hull_min_votes": 1.5})


def test_on_a_table_the_hull_keeps_every_carved_piece(table_capture):
    """On a table the piece vote bought nothing (the real pyramid 4.58 -> 4.56 mm without it): its key changes
    nothing there."""
    scene = load_scene(table_capture)

    def hull_voxels(**overrides):
        config = with_overrides(preset_config("fast"), {**FAST_SMALL, **overrides})
        model = make_fast_model(scene, config, "cpu", RunPlan(steps=1, budget_s=None, seed=0))
        assert model.on_table
        return model.problem.notes["hull_occupied_voxels"]

    assert hull_voxels() == hull_voxels(**{"field.hull_min_votes": 0.0})
