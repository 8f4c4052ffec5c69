"""benchmarks/daemon_overhead.py run as a user runs it: a relative --dir (benchmarks/live.py gives it one under its
own --out), a folder that does not exist yet, a file where a folder should be."""

from __future__ import annotations

import pytest

from benchmark_helpers import load_benchmark


@pytest.fixture(scope="module")
def overhead():
    return load_benchmark("daemon_overhead")


def test_a_relative_dir_that_does_not_exist_yet_is_measured_there(overhead, tmp_path, monkeypatch, capsys):
    # The rig config built under --dir reads its relative paths from its own folder: a relative --dir passed on as it
    # is names every path twice over. A deep one (the pytest folder, then 60 more characters) must work too.
    monkeypatch.chdir(tmp_path)
    deep = "r/" + "s" * 60
    overhead.main(["--dir", deep, "--poses", "3", "--frames", "64"])
    out = capsys.readouterr().out
    assert f"({tmp_path / deep}):" in out  # the folder it measured, named absolute
    assert "histograms written per s" in out
    assert list((tmp_path / deep).iterdir()) == []  # its temporary captures removed


def test_a_file_as_dir_is_a_one_line_usage_error(overhead, tmp_path, capsys):
    (tmp_path / "f").write_text("")
    with pytest.raises(SystemExit) as stop:
        overhead.main(["--dir", str(tmp_path / "f"), "--poses", "3"])
    assert stop.value.code == 2
    assert "is a file, not a folder" in capsys.readouterr().err
