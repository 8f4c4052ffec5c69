"""benchmarks/next_best_view.py: its table (the fewest adaptive views that reach Fibonacci's Chamfer at the largest
count) and the runs it combines."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "next_best_view.py"


@pytest.fixture(scope="module")
def nbv():
    spec = importlib.util.spec_from_file_location("next_best_view", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def fits(rows: dict) -> dict:
    return {"settings": {"views": 128}, "fits": {f"{scene}|{schedule}|{n}": {"chamfer_mm": c}
                                                 for (scene, schedule), by_n in rows.items()
                                                 for n, c in by_n.items()}}


def test_the_table_says_how_many_adaptive_views_reach_fibonacci_at_the_most(nbv):
    data = fits({("cup", "fibonacci"): {16: 9.0, 64: 3.0, 128: 2.0},
                 ("cup", "adaptive-coverage"): {16: 9.0, 64: 1.9, 128: 1.5},
                 ("lamp", "fibonacci"): {16: 9.0, 64: 3.0, 128: 2.0},
                 ("lamp", "adaptive-coverage"): {16: 9.0, 64: 2.5, 128: 2.1}})
    head, rule, *rows = nbv.table(data).splitlines()
    assert [c.strip() for c in head.strip("|").split("|")] == ["scene", "schedule", "16", "64", "128",
                                                               "views to fibonacci@128"]
    cells = {tuple(c.strip() for c in r.strip("|").split("|")[:2]): r.strip("|").split("|")[-1].strip()
             for r in rows}
    assert cells[("cup", "adaptive-coverage")] == "64"
    assert cells[("lamp", "adaptive-coverage")] == "> 128"
    assert cells[("cup", "fibonacci")] == "-"


def test_a_fit_with_no_surface_is_a_cell_of_the_table_and_a_gap_in_the_plot(nbv, tmp_path):
    data = fits({("lamp", "fibonacci"): {16: 46.7, 32: 2.3, 64: 1.4},
                 ("lamp", "adaptive-coverage"): {16: None, 32: 1.4, 64: 1.5}})
    rows = {tuple(c.strip() for c in r.strip("|").split("|")[:2]): [c.strip() for c in r.strip("|").split("|")]
            for r in nbv.table(data).splitlines()[2:]}
    assert rows[("lamp", "adaptive-coverage")][2:] == ["no surface", "1.40", "1.50", "32"]
    nbv.plot(data, tmp_path / "nbv.png")
    assert (tmp_path / "nbv.png").stat().st_size > 0
    assert nbv.chamfer_text({"chamfer_mm": None, "failed": "no surface"}) == "no surface"


def test_combine_refuses_runs_made_with_other_settings(nbv, tmp_path):
    for name, steps in (("a", 800), ("b", 800), ("c", 1000)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps({"settings": {"steps": steps}, "fits": {
            f"{name}|fibonacci|16": {"chamfer_mm": 1.0}}}))
    assert set(nbv.combine([tmp_path / "a", tmp_path / "b"])["fits"]) == {"a|fibonacci|16", "b|fibonacci|16"}
    with pytest.raises(SystemExit, match="other settings"):
        nbv.combine([tmp_path / "a", tmp_path / "c"])



def test_score_picks_counts_to_fit_largest_first_and_only_among_the_counts(nbv):
    args = nbv.parse_args(["--scenes", "builtin:cup", "--counts", "16,32,64", "--score", "16,64"])
    assert args.score == [64, 16]
    assert nbv.parse_args(["--scenes", "builtin:cup", "--counts", "16,32"]).score == [32, 16]
    with pytest.raises(SystemExit):
        nbv.parse_args(["--scenes", "builtin:cup", "--counts", "16,32", "--score", "24"])
