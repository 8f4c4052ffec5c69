"""The fast preset's parts (worker/recon/fast/parts/): one per mechanism, each with its config section, switched off
by one config value, its hooks called in one order, and reported exactly as it ran."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import torch

from spadscan.worker.recon.config import with_overrides
from spadscan.worker.recon.fast import parts as parts_module
from spadscan.worker.recon.fast.model import FastModel, make_fast_model
from spadscan.worker.recon.fast.parts import PARTS, FastPartsConfig, PartConfig
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.presets import preset_config
from spadscan.worker.recon.scene_data import load_scene
from worker_helpers import FAST_SMALL

pytestmark = pytest.mark.usefixtures("one_thread")

NAMES = [cls.name for cls in PARTS]
ON_A_TABLE = ("table", "thin_sheets")
"""Parts that apply only to a scene on a table (the others are tried on the cylinder on the floor)."""
HOOKS = ("before_step", "before_loss", "after_gradient", "after_step")
NEEDS = {"refinement": ("coarse_smoothing",)}
"""Parts that cannot act without another (coarse_smoothing acts on the coarse level only, which refinement makes)."""
CHECK_BEFORE_REFINING = {"parts.dark_restart.check_steps": 3, "parts.dark_restart.trend_steps": 1}
"""FAST_SMALL refines the grid after 4 steps: the dark-restart part reads the albedo on the coarse level, so before."""


def fast(**overrides):
    return with_overrides(preset_config("fast"), {**FAST_SMALL, **CHECK_BEFORE_REFINING, **overrides})


def model_on(capture, config, steps: int):
    model = make_fast_model(load_scene(capture), config, "cpu", RunPlan(steps=steps, budget_s=None, seed=0))
    for _ in range(steps):
        assert math.isfinite(model.step()["loss"])
    return model


def test_every_part_has_one_config_section_in_the_order_its_hooks_run():
    assert NAMES == [f.name for f in dataclasses.fields(FastPartsConfig)]
    assert len(set(NAMES)) == len(NAMES)
    parts = preset_config("fast").parts
    for name in NAMES:
        section = getattr(parts, name)
        assert isinstance(section, PartConfig) and section.enabled is True


@pytest.fixture(scope="module")
def running(cylinder_capture, table_capture):
    """Every part on, 6 steps (the grid is refined after 4), on each scene."""
    return {scene: model_on(capture, fast(), 6)
            for scene, capture in (("floor", cylinder_capture), ("table", table_capture))}


@pytest.mark.parametrize("name", NAMES)
def test_each_part_switches_off_alone_and_the_report_lists_what_ran(name, running, cylinder_capture, table_capture):
    scene = "table" if name in ON_A_TABLE else "floor"
    on = running[scene]
    off = model_on(table_capture if scene == "table" else cylinder_capture, fast(**{f"parts.{name}.enabled": False}), 6)
    ran = [part.name for part in on.parts]
    assert name in ran and on.part(name) is not None
    gone = (name, *NEEDS.get(name, ()))
    assert [part.name for part in off.parts] == [n for n in ran if n not in gone]  # nothing else changes
    for model in (on, off):
        summary = model.summary()
        assert list(summary["parts"]) == [part.name for part in model.parts]  # exactly the parts that ran
        assert set(summary["parts"]) | set(summary["parts_left_out"]) == set(NAMES)
        for part in model.parts:
            assert summary["parts"][part.name]["config"] == dataclasses.asdict(getattr(model.config.parts, part.name))
    assert off.summary()["parts_left_out"][name] == f"switched off (parts.{name}.enabled=false)"
    assert off.part(name) is None


def test_without_refinement_the_coarse_grid_is_the_last_level(cylinder_capture, running):
    off = model_on(cylinder_capture, fast(**{"parts.refinement.enabled": False}), 6)
    on = running["floor"]
    assert (off.level, off.last_level) == (0, True) and (on.level, on.last_level) == (1, True)
    assert max(off.field.counts) < max(on.field.counts)
    assert off.summary()["refined"] is False and on.summary()["parts"]["refinement"]["refined_at_step"] == 4


def test_without_the_table_part_a_table_scene_keeps_its_floor_and_renders_no_plane(table_capture, running):
    off = model_on(table_capture, fast(**{"parts.table.enabled": False}), 2)
    assert off.table is None and off.rays.missed is None and "table_albedo" not in off.step()
    assert off.on_table and off.problem.floor_z == running["table"].problem.floor_z
    assert off.part("empty_space") is not None  # the scene still stands on a table


def test_the_parts_hooks_run_in_their_order_within_each_point_of_the_step(cylinder_capture):
    model = make_fast_model(load_scene(cylinder_capture), fast(), "cpu", RunPlan(steps=1, budget_s=None, seed=0))
    calls = []
    for part in model.parts:
        for hook in HOOKS:
            real = getattr(part, hook)

            def spy(*args, _real=real, _hook=hook, _name=part.name):
                calls.append((_hook, _name))
                return _real(*args)

            setattr(part, hook, spy)
    model.step()
    assert [hook for hook, _ in calls] == sorted((h for h, _ in calls), key=HOOKS.index)  # the step reads top-down
    for hook in HOOKS:
        names = [name for h, name in calls if h == hook]
        assert names == [part.name for part in model.parts]  # every part, in the registry's order


def test_the_empty_space_push_acts_whether_or_not_the_gradient_is_blurred(table_capture):
    # It used to run inside the blur's branch only: with the blur off, the push was silently skipped while the report
    # said it ran.
    fields = {}
    for push in (True, False):
        model = model_on(table_capture, fast(**{"parts.blur.enabled": False, "parts.empty_space.enabled": push}), 1)
        fields[push] = model.field.sdf.detach().clone()
        assert ("empty_space" in model.summary()["parts"]) == push
    moved = (fields[True] - fields[False]).abs()
    assert float(moved.max()) > 0, "the push changed nothing with the blur off"


def test_the_unseen_relaxation_runs_only_without_a_table(running):
    assert running["floor"].part("unseen") is not None
    assert running["table"].part("unseen") is None
    assert "empty-space push" in running["table"].summary()["parts_left_out"]["unseen"]


def test_the_report_lists_only_the_model_terms_the_fit_used(running):
    # The capture's terms said TV on every measured capture (the fast preset has none: its smoothness acts on every
    # capture) and the table on every table scene, even with parts.table.enabled=false (no plane rendered).
    table = running["table"]
    assert table.terms.table and not table.terms.tv
    measured = dataclasses.replace(table.terms, tv=True)  # what choose_terms gives a measured capture
    for on in (True, False):
        model = FastModel(table.problem, fast(**{"parts.table.enabled": on}), seed=0, terms=measured)
        assert model.terms.table is on and (model.table is not None) is on and model.terms.tv is False
        assert model.terms.pileup == measured.pileup and model.terms.crosstalk == measured.crosstalk


def _scene_words(text: str) -> str:
    """'table' for a text that restricts a part to scenes on a table, 'floor' for one without, '' for none."""
    text = text.strip().lower()
    return "table" if text.startswith(("on a table", "scenes on a table")) else \
        "floor" if text.startswith(("without a table", "scenes without a table")) else ""


def test_the_parts_docs_say_on_which_scenes_each_part_runs(running):
    # The module's list said the empty-space push acts on a table; it runs on every scene (docs/fast_method.md).
    ran = {scene: {part.name for part in model.parts} for scene, model in running.items()}
    docs = Path(__file__).resolve().parents[2] / "docs" / "fast_method.md"
    table_rows = {row.split("|")[1].strip(" `"): row.split("|")[3] for row in docs.read_text().splitlines()
                  if row.startswith("| `")}
    listed = {}
    for line in parts_module.__doc__.splitlines():
        words = line.split(maxsplit=2)
        if line.startswith("  ") and words and words[0] in NAMES:
            listed[words[0]] = words[2] if len(words) > 2 else ""
    assert list(listed) == NAMES and list(table_rows) == NAMES
    for name in NAMES:
        for text in (listed[name], table_rows[name]):
            where = _scene_words(text)
            expected = {"table": {"table"}, "floor": {"floor"}, "": {"table", "floor"}}[where]
            assert {scene for scene in ran if name in ran[scene]} == expected, (name, text)
