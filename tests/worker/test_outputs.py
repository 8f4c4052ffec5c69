"""Result folders (`--out`): an empty --out is refused, not taken for the current folder."""

from __future__ import annotations

import pytest

from spadscan.cli import main
from spadscan.protocol.errors import ConfigError
from spadscan.worker.outputs import check_out


def test_check_out_refuses_an_empty_out(tmp_path):
    with pytest.raises(ConfigError, match="^--out is empty: give the folder for the result$"):
        check_out("", False)
    assert check_out(tmp_path / "new", False) == tmp_path / "new"


@pytest.mark.parametrize("command", [["baseline", "reprojection"], ["reconstruct"]])
def test_an_empty_out_is_one_line_and_writes_nothing_into_the_current_folder(tmp_path, monkeypatch, capsys, command):
    """`--out "$OUT"` with OUT unset: baseline wrote mesh.ply, report.json and the rest into the current folder
    and reported `-> ` (and a later --overwrite there put the folder's files at risk)."""
    monkeypatch.chdir(tmp_path)
    assert main([*command, str(tmp_path / "capture"), "--out", ""]) == 1
    assert capsys.readouterr().err == "spadscan: error: --out is empty: give the folder for the result\n"
    assert list(tmp_path.iterdir()) == []
