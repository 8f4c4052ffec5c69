"""`spadscan sweep`'s messages: counts agree with their nouns, and whole numbers print as whole numbers."""

from __future__ import annotations

import pytest

from spadscan.cli import main

ONE_POINT = """
[sweep]
scenes = ["builtin:sphere"]
presets = ["fast"]
baselines = ["space-carving"]

[base]
views = 16

[grid]
views = [16]
"""


def write(tmp_path, text: str):
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path


def test_a_sweep_of_one_point_says_point_not_points(tmp_path, capsys):
    assert main(["sweep", str(write(tmp_path, ONE_POINT)), "--out", str(tmp_path / "out"), "--dry-run"]) == 0
    captured = capsys.readouterr()
    assert "1 grid entry on 1 scene: 1 distinct point; methods fast, space-carving" in captured.err, captured.err
    assert captured.out.splitlines()[-1] == "1 point, 0 done, 1 to run"


def test_the_end_of_a_run_of_one_point_says_point_and_row(tmp_path):
    from spadscan.commands.sweep import finished_lines
    from spadscan.sweep.runner import Summary

    lines = finished_lines(Summary(points=1, earlier=0, ran=1, done=1, rows=1), {}, tmp_path / "out")
    assert lines == ["1 point: 0 done earlier, 1 run now (1 done, 0 failed)",
                     f"results: {tmp_path / 'out' / 'results.csv'} (1 row); plot: spadscan sweep-plot "
                     f"{tmp_path / 'out'}"]
    lines = finished_lines(Summary(points=3, earlier=1, ran=2, done=2, rows=4), {}, tmp_path / "out")
    assert lines[0] == "3 points: 1 done earlier, 2 run now (2 done, 0 failed)" and "(4 rows)" in lines[1]


@pytest.mark.parametrize("where, text, value", [
    ("[base]", "[base]\nseed = 99999999999999999999\n", "99999999999999999999"),
    ("[grid] seed", "[grid]\nseed = [0, 99999999999999999999]\n", "99999999999999999999"),
    ("[base]", "[base]\nseed = 1e20\n", "100000000000000000000"),  # a whole float is read as the integer
])
def test_an_integer_out_of_range_and_its_bounds_print_as_integers(tmp_path, capsys, where, text, value):
    path = write(tmp_path, '[sweep]\nscenes = ["builtin:sphere"]\n' + text)
    assert main(["sweep", str(path), "--out", str(tmp_path / "out"), "--dry-run"]) == 1
    err = capsys.readouterr().err
    assert err == (f"spadscan: error: {path}: {where}: seed = {value} is out of range (must be >= 0 and <= "
                   f"9223372036854775807)\n")


def test_a_point_with_a_large_integer_is_named_with_every_digit(tmp_path, capsys):
    path = write(tmp_path, '[sweep]\nscenes = ["builtin:sphere"]\n[grid]\nseed = [0, 123456789]\n')
    assert main(["sweep", str(path), "--out", str(tmp_path / "out"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "builtin:sphere seed=123456789" in out, out


def test_a_sweep_without_a_grid_says_it_runs_the_base_condition_alone(tmp_path, capsys):
    for text in ('[sweep]\nscenes = ["builtin:sphere"]\n', '[sweep]\nscenes = ["builtin:sphere"]\n[grid]\n'):
        assert main(["sweep", str(write(tmp_path, text)), "--out", str(tmp_path / "out"), "--dry-run"]) == 0
        err = capsys.readouterr().err
        assert "1 grid entry on 1 scene: 1 distinct point; methods fast, reprojection, space-carving (no [grid]: the " \
               "base condition alone)" in err, err
