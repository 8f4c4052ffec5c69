"""A folder option given empty (`--out "$OUT"` with OUT unset) is refused in one line by every command, before it
runs: as a path it would be the current folder, where baseline wrote its result among the user's files."""

from __future__ import annotations

import pytest

from spadscan.cli import main


@pytest.mark.parametrize("argv", [
    ["simulate", "builtin:sphere", "--out", "", "--views", "2", "--no-progress"],
    ["import-lcspc", "scene.json", "--out", ""],
    ["baseline", "reprojection", "capture", "--out", ""],
    ["reconstruct", "capture", "--out="],
    ["sweep", "sweep.toml", "--out", ""],
    ["demo", "--out", ""],
    ["dashboard", "--root", ""],
    ["worker", "--root", "", "--once"],
])
def test_an_empty_folder_option_is_one_line_and_writes_nothing(tmp_path, monkeypatch, capsys, argv):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 1
    name = next(token.partition("=")[0] for token in argv if token.partition("=")[0] in ("--out", "--root"))
    assert capsys.readouterr().err == f"spadscan: error: {name} is empty (an unset shell variable?): give the folder\n"
    assert list(tmp_path.iterdir()) == []
