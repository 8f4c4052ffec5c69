"""Opening the solid behind phantom surface (worker/recon/fast/parts/openings.py): the proposal field, the evidence's
classes, and the part's rounds of proposals kept only where the likelihood prefers them."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from spadscan.protocol.errors import ConfigError
from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.fast.evidence import ReturnEvidence
from spadscan.worker.recon.fast.grid_ops import redistanced
from spadscan.worker.recon.fast.model import FastModel, make_fast_model
from spadscan.worker.recon.fast.parts.openings import Openings, opened_field, opening_distances, surface_classes
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.presets import preset_config
from spadscan.worker.recon.scene_data import load_scene
from worker_helpers import FAST_SMALL, blank_histograms

VOXEL = 0.01


def slab(n: int = 20, top: int = 15) -> torch.Tensor:
    """(n, n, n) SDF (z, y, x), metres: solid below node layer `top`."""
    z = torch.arange(n, dtype=torch.float32)[:, None, None].expand(n, n, n)
    return (z - top) * VOXEL


def patch(n: int = 20, z: int = 15, lo: int = 6, hi: int = 14) -> torch.Tensor:
    out = torch.zeros(n, n, n, dtype=torch.bool)
    out[z, lo:hi, lo:hi] = True
    return out


def test_the_solid_behind_flagged_surface_opens_as_deep_as_asked_and_nowhere_else():
    sdf, flagged = slab(), patch()
    distances = opening_distances(flagged, torch.zeros_like(flagged), VOXEL)
    assert bool(torch.isinf(distances[1]).all())  # nothing supported: every node is infinitely far from it
    opened, n = opened_field(sdf, flagged, distances, 0.045, 0.0)
    assert n > 0 and n == int((opened > sdf).sum())
    assert bool((opened >= sdf).all()) and torch.isfinite(opened).all()  # an opening only ever raises the field
    centre = opened[:, 10, 10]
    assert bool((centre[11:15] > 0).all())  # 1-4 voxels under the patch: empty now
    assert bool((centre[:10] < 0).all())  # 5 voxels and deeper: still solid
    assert float(centre[12]) == pytest.approx(0.045 - 0.03)  # a distance field of the opened region
    assert torch.equal(opened[:, 0, 0], sdf[:, 0, 0])  # far from the patch: unchanged
    deeper, m = opened_field(sdf, flagged, distances, 0.085, 0.0)
    assert m > n and bool((deeper[7:15, 10, 10] > 0).all()) and float(deeper[6, 10, 10]) < 0


def test_solid_near_supported_surface_is_kept_and_nothing_flagged_changes_nothing():
    sdf, flagged = slab(), patch()
    supported = torch.zeros_like(flagged)
    supported[11, :, :] = True  # a wall the data holds, 4 voxels under the flagged patch
    opened, _ = opened_field(sdf, flagged, opening_distances(flagged, supported, VOXEL), 0.085, 0.015)
    centre = opened[:, 10, 10]
    assert bool((centre[13:15] > 0).all())  # more than 1.5 cm from the supported layer: opened
    assert torch.equal(centre[:13], sdf[:13, 10, 10])  # within 1.5 cm of it, and beyond it: untouched
    nothing = torch.zeros_like(flagged)
    same, n = opened_field(sdf, nothing, opening_distances(nothing, supported, VOXEL), 0.085, 0.015)
    assert n == 0 and torch.equal(same, sdf)
    with pytest.raises(ValueError, match="one shape"):
        opening_distances(flagged[:-1], supported, VOXEL)
    with pytest.raises(ValueError, match="one shape"):
        opened_field(sdf[:-1], flagged, opening_distances(flagged, supported, VOXEL), 0.04, 0.0)
    with pytest.raises(ValueError, match="depth"):
        opened_field(sdf, flagged, opening_distances(flagged, supported, VOXEL), -0.04, 0.0)


def test_evidence_classes_flagged_and_supported_nodes_and_keeps_its_sums():
    ev = ReturnEvidence((3, 3, 3), "cpu")
    origin = torch.zeros(3)
    at = lambda x: torch.tensor([[x * VOXEL, 0.0, 0.0]])  # noqa: E731
    for ratio, node, hits in ((0.3, 0, 3), (0.9, 1, 3), (0.7, 2, 3)):
        for _ in range(hits):
            ev.add(at(node), torch.tensor([math.log(ratio)]), origin, VOXEL)
    flagged, supported = ev.classify(3, 0.6, 0.8)
    assert flagged[0, 0].tolist() == [True, False, False] and supported[0, 0].tolist() == [False, True, False]
    assert int(flagged.sum()) == 1 and int(supported.sum()) == 1  # 0.7 is neither
    assert int(ev.hits.sum()) == 9  # classify keeps the sums; take starts afresh
    assert int(ev.classify(4, 0.6, 0.8)[0].sum()) == 0  # too few returns for either class
    with pytest.raises(ValueError, match="ratios"):
        ev.classify(3, 0.9, 0.8)


def test_only_nodes_at_the_surface_as_it_is_now_are_classed():
    sdf = slab()  # surface at node layer 15
    ev = ReturnEvidence(tuple(sdf.shape), "cpu")
    origin = torch.zeros(3)
    for z, x, ratio in ((15, 5, 0.3), (19, 6, 0.3), (15, 7, 0.9), (11, 8, 0.9)):  # at the surface, 4 voxels off it
        for _ in range(3):
            ev.add(torch.tensor([[x * VOXEL, 5 * VOXEL, z * VOXEL]]), torch.tensor([math.log(ratio)]), origin, VOXEL)
    everywhere = ev.classify(3, 0.6, 0.8)
    assert [int(c.sum()) for c in everywhere] == [2, 2]
    flagged, supported = surface_classes(ev, sdf, VOXEL, 3, 0.6, 0.8)
    assert torch.nonzero(flagged).tolist() == [[15, 5, 5]] and torch.nonzero(supported).tolist() == [[15, 5, 7]]
    with pytest.raises(ValueError, match="one shape"):
        surface_classes(ev, sdf[:-1], VOXEL, 3, 0.6, 0.8)
    with pytest.raises(ValueError, match="voxel"):
        surface_classes(ev, sdf, 0.0, 3, 0.6, 0.8)


SMALL = {**FAST_SMALL, "schedule.views_per_step": 8, "parts.erosion.min_hits": 1, "parts.openings.min_hits": 1,
         "parts.openings.every_steps": 2, "parts.openings.passes": 1, "parts.openings.min_flagged": 1}


def test_an_opening_the_likelihood_prefers_is_kept_and_the_mesh_average_follows_it(cylinder_capture):
    scene = load_scene(cylinder_capture)
    model = make_fast_model(scene, with_overrides(preset_config("fast"), SMALL), "cpu",
                            RunPlan(steps=2, budget_s=None, seed=0))
    blank_histograms(model)
    solid_before = int((model.field.sdf.detach() < 0).sum())
    for _ in range(2):
        assert math.isfinite(model.step()["loss"])
    openings = model.part("openings")
    (round_,) = openings.rounds
    assert round_["step"] == 2 and round_["flagged"] > 0
    assert round_["depth_m"] in preset_config("fast").parts.openings.depths_m
    assert round_["deviance_after"] < round_["deviance"] - openings.config.min_gain
    assert round_["seconds"] > 0
    reported = model.summary()["parts"]["openings"]
    assert openings.opened_nodes == round_["opened"] > 0 and reported["opened_nodes"] == openings.opened_nodes
    assert reported["rounds"] == [round_]
    assert int((model.field.sdf.detach() < 0).sum()) < solid_before
    assert torch.equal(model.mesh_field().sdf.detach(), model.field.sdf.detach())  # the average restarts at the jump
    assert torch.isfinite(model.field.sdf.detach()).all()


@pytest.mark.parametrize("redistance", [True, False])
def test_a_kept_opening_leaves_a_signed_distance_unless_told_not_to(cylinder_capture, redistance):
    scene = load_scene(cylinder_capture)
    config = with_overrides(preset_config("fast"), {**SMALL, "parts.openings.redistance": redistance})
    model = make_fast_model(scene, config, "cpu", RunPlan(steps=2, budget_s=None, seed=0))
    blank_histograms(model)
    for _ in range(2):
        model.step()
    assert "depth_m" in model.part("openings").rounds[0]
    grid = model.field.sdf.detach()[0, 0].numpy()
    again = redistanced(grid, model.field.voxel)
    # Redistanced, the grid is its own redistancing; as opened, its values rise towards the opened surface.
    assert (abs(again - grid).max() < 1e-6) == redistance


def test_redistancing_keeps_every_sign_and_the_surface_and_makes_the_rest_a_distance():
    sdf = slab()  # solid below layer 15, its surface on that layer
    junk = sdf.clone()
    junk[18:] = 0.5  # far above: no distance
    junk[:10] = -0.001  # deep inside: barely solid, as an opening leaves the solid beyond its depth
    out = torch.from_numpy(redistanced(junk.numpy(), VOXEL))
    assert torch.equal(out < 0, junk < 0)
    assert torch.equal(out[14:16], junk[14:16])  # the surface's sub-voxel position stays (the layers beside it)
    column = out[:, 10, 10]
    assert torch.allclose(column[17:] - column[16:-1], torch.full((3,), VOXEL))  # one voxel a node outside
    assert float(column[16]) == pytest.approx(1.5 * VOXEL)  # half a voxel past the nearest solid node's
    assert torch.allclose(column[1:14] - column[:13], torch.full((13,), VOXEL))  # and inside, though the junk
    assert float(column[0]) == pytest.approx(-14.5 * VOXEL)  # there was within a voxel of zero
    for same in (torch.full((4, 4, 4), 0.3), torch.full((4, 4, 4), -0.3)):  # one sign only: nothing to measure to
        assert torch.equal(torch.from_numpy(redistanced(same.numpy(), VOXEL)), same)
    with pytest.raises(ValueError, match="voxel"):
        redistanced(sdf.numpy(), 0.0)


def test_a_round_weighs_the_returns_of_the_training_steps_in_its_window_only(cylinder_capture):
    # 24 views at 8 a step: one pass's worth is 3 steps, so the round at step 6 weighs the returns of steps 4-6. The
    # erosion falls on step 6 too, and comes after the round: the round still finds the erosion's evidence untaken.
    scene = load_scene(cylinder_capture)
    config = with_overrides(preset_config("fast"), {**SMALL, "parts.refinement.enabled": False,
                                                    "parts.openings.every_steps": 6, "parts.erosion.every_steps": 6})
    model = make_fast_model(scene, config, "cpu", RunPlan(steps=6, budget_s=None, seed=0))
    blank_histograms(model)
    openings, erosion = model.part("openings"), model.part("erosion")
    assert openings.window == 3
    seen, round_ = [], openings._round

    def spy(m):
        # The erosion's evidence holds every step's returns so far (it is first taken after this round).
        seen.append((float(openings.evidence.hits.sum()), float(erosion.evidence.hits.sum())))
        round_(m)

    openings._round = spy
    totals = []
    for _ in range(6):
        model.step()
        totals.append(float(erosion.evidence.hits.sum()))
    assert len(seen) == 1 and len(openings.rounds) == 1
    window, all_steps = seen[0]
    assert 0 < window == all_steps - totals[2] < all_steps
    assert openings.rounds[0]["flagged"] > 0 and openings.evidence is None  # a round consumes its evidence
    assert "depth_m" in openings.rounds[0] and totals[5] == 0  # a kept jump restarts the erosion's evidence


@pytest.mark.parametrize("deviances, kept", [
    ((1.0, 0.90, 0.80, 0.85), 0.08),  # every depth gains enough: the deepest, though 4 cm gains more
    ((1.0, 0.90, 0.80, 0.999), 0.04),  # 8 cm gains too little: the deepest of those that gain enough
    ((1.0, 0.999, 0.998, 0.997), None),  # none does: the field stays as it was
])
def test_the_deepest_opening_that_gains_enough_is_kept(cylinder_capture, deviances, kept):
    scene = load_scene(cylinder_capture)
    config = with_overrides(preset_config("fast"), {**SMALL, "parts.openings.depths_m": [0.08, 0.02, 0.04],
                                                    "parts.openings.min_gain": 0.05})
    model = make_fast_model(scene, config, "cpu", RunPlan(steps=2, budget_s=None, seed=0))
    blank_histograms(model)
    model.step()
    rendered = []  # the solid nodes of each field the round renders: the current one, then each proposal

    def deviance(seed):
        rendered.append(int((model.field.sdf.detach() < 0).sum()))
        return deviances[len(rendered) - 1]

    model.deviance_all_views = deviance
    model.step()
    (round_,) = model.part("openings").rounds
    assert round_["deviance"] == 1.0 and round_["proposals"] == {"0.02": deviances[1], "0.04": deviances[2],
                                                                 "0.08": deviances[3]}
    assert rendered[0] > rendered[1] > rendered[2] > rendered[3]  # proposed shallow to deep, whatever the order
    assert round_.get("depth_m") == kept
    solid_now = int((model.field.sdf.detach() < 0).sum())
    if kept is None:
        assert solid_now == rendered[0] and "deviance_after" not in round_
    else:
        index = 1 + [0.02, 0.04, 0.08].index(kept)
        assert round_["deviance_after"] == deviances[index] and solid_now == rendered[index]


def test_rounds_that_gain_nothing_are_undone_and_stop_after_the_patience(cylinder_capture):
    scene = load_scene(cylinder_capture)
    config = with_overrides(preset_config("fast"), {**SMALL, "parts.openings.min_gain": 1e9,
                                                    "parts.openings.patience": 2})
    model = make_fast_model(scene, config, "cpu", RunPlan(steps=8, budget_s=None, seed=0))
    blank_histograms(model)
    for _ in range(3):
        model.step()
    model.step()  # step 4: the second round, whose proposals are all rejected and undone
    after_rounds = model.field.sdf.detach().clone()
    openings = model.part("openings")
    assert len(openings.rounds) == 2 and "depth_m" not in openings.rounds[1] and openings.opened_nodes == 0
    assert not openings.proposing and not openings.wants_returns
    for _ in range(4):
        model.step()
    assert len(openings.rounds) == 2  # no rounds after the patience ran out
    # A rejected round leaves the grid as the step made it: the same as a run with the part switched off.
    off = make_fast_model(scene, with_overrides(config, {"parts.openings.enabled": False}), "cpu",
                          RunPlan(steps=8, budget_s=None, seed=0))
    blank_histograms(off)
    for _ in range(4):
        off.step()
    assert off.part("openings") is None and torch.equal(off.field.sdf.detach(), after_rounds)


def test_a_round_with_fewer_flagged_nodes_than_the_minimum_proposes_nothing(cylinder_capture):
    scene = load_scene(cylinder_capture)
    config = with_overrides(preset_config("fast"), {**SMALL, "parts.openings.min_gain": 0.0})
    runs = {}
    for minimum in (1, 10**9):
        model = make_fast_model(scene, with_overrides(config, {"parts.openings.min_flagged": minimum}), "cpu",
                                RunPlan(steps=2, budget_s=None, seed=0))
        blank_histograms(model)
        for _ in range(2):
            model.step()
        runs[minimum] = model.part("openings")
    assert runs[1].rounds[0]["flagged"] > 0 and "depth_m" in runs[1].rounds[0]
    (round_,) = runs[10**9].rounds
    assert round_["flagged"] == runs[1].rounds[0]["flagged"] and "depth_m" not in round_
    assert runs[10**9].opened_nodes == 0 and runs[10**9].misses == 1


def test_the_floor_is_kept_like_supported_surface(cylinder_capture):
    scene = load_scene(cylinder_capture)
    model = make_fast_model(scene, with_overrides(preset_config("fast"), SMALL), "cpu",
                            RunPlan(steps=1, budget_s=None, seed=0))
    assert model.problem.floor_z == 0.0
    sdf = model.field.sdf.detach()[0, 0]
    flagged, nothing = torch.zeros_like(sdf, dtype=torch.bool), torch.zeros_like(sdf, dtype=torch.bool)
    flagged[-3, 5, 5] = True
    d_flagged, d_supported = Openings._distances(model, flagged, nothing)
    heights = model.field.origin[2] + torch.arange(sdf.shape[0]) * model.field.voxel
    assert torch.allclose(d_supported[:, 2, 7], heights.clamp(min=0.0), atol=1e-6)
    assert float(d_flagged[-3, 5, 5]) == 0.0
    opened, _ = opened_field(sdf - 1.0, flagged, (d_flagged, d_supported), 10.0, 0.02)  # all solid, opened 10 m deep
    low = heights < 0.02
    assert bool(low.any()) and torch.equal(opened[low], (sdf - 1.0)[low])  # within 2 cm of the floor: kept
    assert bool((opened[~low] > 0).all())


def test_no_openings_on_measured_captures_and_bad_settings_are_one_line_errors(cylinder_capture):
    scene = load_scene(cylinder_capture)
    config = with_overrides(preset_config("fast"), SMALL)
    model = make_fast_model(scene, config, "cpu", RunPlan(steps=1, budget_s=None, seed=0))
    measured = FastModel(dataclasses.replace(model.problem, measured=True), config, seed=0, terms=model.terms)
    assert measured.part("openings") is None and "measured" in measured.summary()["parts_left_out"]["openings"]
    for key, bad in (("parts.openings.every_steps", 0), ("parts.openings.depths_m", [0.02, -0.01]),
                     ("parts.openings.depths_m", []), ("parts.openings.keep_m", 0.5),
                     ("parts.openings.keep_ratio", 0.5), ("parts.openings.passes", 0),
                     ("parts.openings.min_gain", -1.0), ("parts.openings.min_flagged", 0)):
        with pytest.raises(ConfigError, match=key.split(".")[-1]):
            make_fast_model(scene, _unchecked(config, {key: bad}), "cpu", RunPlan(steps=1, budget_s=None, seed=0))
        with pytest.raises(ConfigError, match=key.split(".")[-1]):  # refused before any capture is loaded, too
            with_overrides(config, {key: bad})


def _unchecked(config, values: dict):
    """A copy of config with dotted keys set as given, past `with_overrides`' checks."""
    import copy

    config = copy.deepcopy(config)
    for key, value in values.items():
        *path, name = key.split(".")
        obj = config
        for part in path:
            obj = getattr(obj, part)
        setattr(obj, name, tuple(value) if isinstance(value, list) else value)
    return config
