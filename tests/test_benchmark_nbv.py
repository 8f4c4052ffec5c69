"""benchmarks/next_best_view.py: its table (the fewest adaptive views that reach Fibonacci's Chamfer at the largest
count) and the runs it combines."""

from __future__ import annotations

import json

import pytest

from benchmark_helpers import load_benchmark


@pytest.fixture(scope="module")
def nbv():
    return load_benchmark("next_best_view")


def fits(rows: dict, seed: int = 0) -> dict:
    return {"settings": {"views": 128}, "fits": {f"{scene}|{schedule}|{n}|{seed}": {"chamfer_mm": c}
                                                 for (scene, schedule), by_n in rows.items()
                                                 for n, c in by_n.items()}}


def cells_of(text: str) -> dict:
    return {tuple(c.strip() for c in r.strip("|").split("|")[:2]): [c.strip() for c in r.strip("|").split("|")[2:]]
            for r in text.splitlines()[2:] if r.startswith("|")}


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
            f"{name}|fibonacci|16|0": {"chamfer_mm": 1.0}}}))
    assert set(nbv.combine([tmp_path / "a", tmp_path / "b"])["fits"]) == {"a|fibonacci|16|0", "b|fibonacci|16|0"}
    with pytest.raises(SystemExit, match="other settings"):
        nbv.combine([tmp_path / "a", tmp_path / "c"])


def test_combine_says_which_argument_is_not_a_run_folder(nbv, tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "results.json").write_text(json.dumps({"settings": {"steps": 800}, "fits": {}}))
    (tmp_path / "a.log").write_text("a log, not a run folder")
    for other in (tmp_path / "a.log", tmp_path / "missing"):
        with pytest.raises(SystemExit, match=f"{other.name}: no results.json here"):
            nbv.combine([tmp_path / "a", other])


def test_several_seeds_give_the_median_and_its_range_and_decide_the_goal_by_the_median(nbv):
    per_seed = [({"fibonacci": {64: 3.6, 128: 2.75}, "adaptive-coverage": {64: 4.33}}),
                ({"fibonacci": {64: 4.5, 128: 2.81}, "adaptive-coverage": {64: 2.43}}),
                ({"fibonacci": {64: 4.4, 128: 2.84}, "adaptive-coverage": {64: None}})]
    data = {"settings": {}, "fits": {}}
    for seed, rows in enumerate(per_seed):
        data["fits"].update(fits({("cup", k): v for k, v in rows.items()}, seed)["fits"])
    text = nbv.table(data)
    cells = cells_of(text)
    assert cells[("cup", "fibonacci")] == ["4.40 (3.60-4.50)", "2.81 (2.75-2.84)", "-"]
    # The median of 2.43, 4.33 and no surface is 4.33: over Fibonacci's 2.81, so the goal is not reached.
    assert cells[("cup", "adaptive-coverage")] == ["4.33 (2.43-no surface)", "", "> 64"]
    assert "median of seeds 0, 1, 2" in text
    data["fits"]["cup|adaptive-coverage|64|2"] = {"chamfer_mm": 2.09}
    assert cells_of(nbv.table(data))[("cup", "adaptive-coverage")] == ["2.43 (2.09-4.33)", "", "64"]


def test_combine_takes_the_seed_of_a_run_made_before_seeds_were_in_the_keys(nbv, tmp_path):
    for name, seed in (("old", 0), ("new", 1)):
        (tmp_path / name).mkdir()
    (tmp_path / "old" / "results.json").write_text(json.dumps({"settings": {"steps": 500, "seed": 0}, "fits": {
        "cup|fibonacci|64": {"chamfer_mm": 3.59}}}))
    (tmp_path / "new" / "results.json").write_text(json.dumps({"settings": {"steps": 500}, "fits": {
        "cup|fibonacci|64|1": {"chamfer_mm": 4.50}}}))
    data = nbv.combine([tmp_path / "old", tmp_path / "new"])
    assert data["fits"] == {"cup|fibonacci|64|0": {"chamfer_mm": 3.59}, "cup|fibonacci|64|1": {"chamfer_mm": 4.50}}
    assert cells_of(nbv.table(data))[("cup", "fibonacci")] == ["4.04 (3.59-4.50)", "-"]



def test_seeds_are_a_list_of_integers(nbv):
    assert nbv.parse_args(["--scenes", "builtin:cup", "--seeds", "2,0,1"]).seeds == [0, 1, 2]
    assert nbv.parse_args(["--scenes", "builtin:cup"]).seeds == [0]
    with pytest.raises(SystemExit):
        nbv.parse_args(["--scenes", "builtin:cup", "--seeds", "one"])


def test_score_picks_counts_to_fit_largest_first_and_only_among_the_counts(nbv):
    args = nbv.parse_args(["--scenes", "builtin:cup", "--counts", "16,32,64", "--score", "16,64"])
    assert args.score == [64, 16]
    assert nbv.parse_args(["--scenes", "builtin:cup", "--counts", "16,32"]).score == [32, 16]
    with pytest.raises(SystemExit):
        nbv.parse_args(["--scenes", "builtin:cup", "--counts", "16,32", "--score", "24"])


def cached(nbv, out, **changes) -> dict:
    """A results.json in `out` holding two fits made with the default settings (`changes` applied to them)."""
    out.mkdir(exist_ok=True)
    settings = {**nbv.settings_of(nbv.parse_args(["--scenes", "builtin:cup", "--out", str(out)])), **changes}
    data = {"settings": settings, "fits": {"cup|fibonacci|64|0": {"chamfer_mm": 3.59},
                                           "cup|fibonacci|128|0": {"chamfer_mm": 2.75}}}
    (out / "results.json").write_text(json.dumps(data))
    return data


def test_an_out_holding_fits_made_with_other_settings_is_refused_not_reset(nbv, tmp_path, capsys):
    out = tmp_path / "nbv"
    data = cached(nbv, out)
    with pytest.raises(SystemExit) as stop:
        nbv.main(["--scenes", "builtin:sphere", "--counts", "8", "--views", "8", "--steps", "2", "--measures", "",
                  "--out", str(out)])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "holds 2 fits made with other settings" in err and "--views 128, not 8; --steps 1000, not 2" in err, err
    assert "--overwrite" in err and "Traceback" not in err
    assert json.loads((out / "results.json").read_text()) == data  # nothing lost
    # A Results of other settings is an error, never a silent reset to no fits.
    with pytest.raises(ValueError, match="other settings"):
        nbv.Results(out / "results.json", {**data["settings"], "steps": 2})
    assert json.loads((out / "results.json").read_text()) == data


def test_the_same_settings_reuse_the_fits_and_overwrite_discards_them(nbv, tmp_path):
    out = tmp_path / "nbv"
    data = cached(nbv, out)
    args = nbv.parse_args(["--scenes", "builtin:cup", "--out", str(out)])
    assert set(nbv.Results(out / "results.json", nbv.settings_of(args)).data["fits"]) == set(data["fits"])
    args = nbv.parse_args(["--scenes", "builtin:cup", "--steps", "2", "--out", str(out), "--overwrite"])
    assert nbv.Results(out / "results.json", nbv.settings_of(args), overwrite=True).data["fits"] == {}


def test_an_unreadable_results_json_or_a_file_as_out_is_a_one_line_error(nbv, tmp_path, capsys):
    (tmp_path / "nbv").mkdir()
    (tmp_path / "nbv" / "results.json").write_text("{half")
    (tmp_path / "afile").write_text("")
    for out, says in ((tmp_path / "nbv", "does not read as this script's"), (tmp_path / "afile", "not a folder")):
        with pytest.raises(SystemExit):
            nbv.parse_args(["--scenes", "builtin:cup", "--out", str(out)])
        err = capsys.readouterr().err
        assert "Traceback" not in err and says in err.strip().splitlines()[-1], err


def test_a_scene_that_does_not_load_is_refused_before_any_fit(nbv, tmp_path, capsys):
    """Every scene is read first: a misspelt last one is one line before the first one's fits, and --out stays
    unmade."""
    with pytest.raises(SystemExit) as exit_:
        nbv.main(["--scenes", "builtin:sphere", "builtin:sphre", "--out", str(tmp_path / "out")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert ": error: --scenes builtin:sphre: unknown built-in scene 'sphre'" in err, err
    assert not (tmp_path / "out").exists()


def test_ctrl_c_says_where_the_finished_fits_are_and_exits_130(nbv, tmp_path, capsys, monkeypatch):
    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(nbv, "run", interrupted)
    assert nbv.main(["--scenes", "builtin:sphere", "--out", str(tmp_path / "out")]) == 130
    err = capsys.readouterr().err
    assert "interrupted" in err and "results.json keeps the fits that finished" in err and "Traceback" not in err
