"""A folder option or a positional argument given empty (`--out "$OUT"`, `"$CAPTURE"` with it unset) is refused in one
line by every command, before it runs: as a path it would be the current folder, where baseline wrote its result among
the user's files."""

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


@pytest.mark.parametrize("argv, name", [
    (["reconstruct", "", "--out", "x"], "CAPTURE"),
    (["baseline", "space-carving", "", "--out", "x"], "CAPTURE"),
    (["eval", "", "--gt", "builtin:sphere"], "MESH"),
    (["import-lcspc", "", "--out", "x"], "FILE.json"),
    (["simulate", "", "--out", "x"], "MESH"),
    (["sweep", "", "--out", "x"], "SWEEP.toml"),
    (["sweep-plot", ""], "DIR"),
    (["calibrate", "hand-eye", ""], "CAPTURE"),
    (["ctl", "wait", ""], "NAME"),
])
def test_an_empty_path_argument_is_named_in_one_line_and_writes_nothing(tmp_path, monkeypatch, capsys, argv, name):
    """Not '.: is a folder' or 'x lies inside the capture ': the argument the user left empty, by its name."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 1
    assert capsys.readouterr().err == f"spadscan: error: {name} is empty (an unset shell variable?)\n"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [
    ["daemon", "--config", "", "--check"],
    ["eval", "mesh.ply", "--gt="],
    ["reconstruct", "capture", "--out", "x", "--gt", ""],
    ["baseline", "reprojection", "capture", "--out", "x", "--gt", ""],
])
def test_an_empty_file_option_is_named_in_one_line_and_writes_nothing(tmp_path, monkeypatch, capsys, argv):
    """Not '.: cannot read ([Errno 21] Is a directory: '.')' nor '.: is a folder, not a mesh file'."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 1
    name = next(token.partition("=")[0] for token in argv if token.partition("=")[0] in ("--config", "--gt"))
    assert capsys.readouterr().err == f"spadscan: error: {name} is empty (an unset shell variable?): give the file\n"
    assert list(tmp_path.iterdir()) == []
