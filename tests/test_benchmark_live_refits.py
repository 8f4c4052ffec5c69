"""benchmarks/live_refits.py: the rows are about the scan --scene and --views name (an --out holding another scan, or
an earlier run's replays, is refused in one line before anything runs), and a rule whose scan completed before its
live fit started is a row that says so, never a traceback.

The live job itself (tens of seconds) is stood in for where a test needs one; the scans are real, of two views."""

from __future__ import annotations

import json
import shutil
import signal

import pytest
import torch

from benchmark_helpers import load_benchmark


@pytest.fixture(scope="module")
def refits():
    return load_benchmark("live_refits")


@pytest.fixture(scope="module")
def sphere_scan(refits, tmp_path_factory):
    """The scan live_refits simulates for --scene sphere --views 2."""
    source = tmp_path_factory.mktemp("live-refits") / "source"
    refits.simulate("sphere", 2, source)
    return source


@pytest.fixture
def out(sphere_scan, tmp_path):
    """An --out that an earlier call with --scene sphere --views 2 left its scan in."""
    shutil.copytree(sphere_scan, tmp_path / "out" / "source")
    return tmp_path / "out"


@pytest.fixture(autouse=True)
def process_wide(monkeypatch):
    """What main sets for its whole process is not set for the tests after this one."""
    monkeypatch.setattr(signal, "signal", lambda signum, handler: signal.getsignal(signum))
    monkeypatch.setattr(torch, "set_num_threads", lambda n: None)


def call(refits, argv) -> int:
    try:
        return refits.main([str(a) for a in argv])
    except SystemExit as exc:
        return exc.code


def no_follow(*args, **kwargs):
    raise AssertionError("a rule was followed")


def error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return err.strip().splitlines()[-1]


@pytest.mark.parametrize("argv, says", [
    (["--scene", "mug", "--views", 2], "a scan of sphere with 2 views (tmf8820), not of mug with 2 views"),
    (["--scene", "sphere", "--views", 128], "a scan of sphere with 2 views (tmf8820), not of sphere with 128 views"),
])
def test_an_out_holding_the_scan_of_another_scene_or_view_count_is_refused(refits, out, monkeypatch, capsys,
                                                                           argv, says):
    monkeypatch.setattr(refits, "follow", no_follow)
    monkeypatch.setattr(refits, "simulate", no_follow)
    assert call(refits, [*argv, "--every-s", 0.3, "--out", out]) == 2
    line = error_line(capsys)
    assert says in line and "choose another --out" in line, line
    assert sorted(p.name for p in out.iterdir()) == ["source"]


def test_a_scan_cut_short_is_refused(refits, out, monkeypatch, capsys):
    manifest = json.loads((out / "source" / "scan.json").read_text())
    (out / "source" / "scan.json").write_text(json.dumps({**manifest, "state": "running"}))
    monkeypatch.setattr(refits, "follow", no_follow)
    assert call(refits, ["--scene", "sphere", "--views", 2, "--out", out]) == 2
    assert "not complete" in error_line(capsys)


def test_an_earlier_runs_replays_are_refused_unless_overwrite(refits, out, monkeypatch, capsys):
    (out / "former" / "recon").mkdir(parents=True)
    (out / "refits.json").write_text("[]")
    monkeypatch.setattr(refits, "follow", no_follow)
    assert call(refits, ["--scene", "sphere", "--views", 2, "--out", out]) == 2
    line = error_line(capsys)
    assert "already holds former/ of an earlier run" in line and "--overwrite" in line, line

    followed = []

    def follow(source, root, name, every_s):
        assert not (root / name).exists()  # the earlier replay went first: CaptureWriter.create needs a new folder
        followed.append(name)
        return {"rule": name, "wall_s": 1.0, "refits": 1, "refit_s": 0.5, "train_s": 0.5, "steps": 10,
                "views_used": 2, "chamfer_mm": None}

    monkeypatch.setattr(refits, "follow", follow)
    assert call(refits, ["--scene", "sphere", "--views", 2, "--out", out, "--overwrite"]) == 0
    assert followed == ["former", "today"]
    assert (out / "source" / "scan.json").is_file()  # the scan is reused, not simulated again


def test_an_out_that_is_a_file_is_refused(refits, tmp_path, monkeypatch, capsys):
    (tmp_path / "afile").write_text("")
    monkeypatch.setattr(refits, "simulate", no_follow)
    assert call(refits, ["--scene", "sphere", "--out", tmp_path / "afile"]) == 2
    assert "exists and is not a folder" in error_line(capsys)


def test_every_s_must_be_positive(refits, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(refits, "simulate", no_follow)
    assert call(refits, ["--scene", "sphere", "--every-s", 0, "--out", tmp_path / "out"]) == 2
    assert "--every-s a finite number of seconds > 0" in error_line(capsys)
    assert not (tmp_path / "out").exists()


def test_a_scan_that_completed_before_the_live_fit_is_a_row_saying_so(refits, out, monkeypatch, capsys):
    def execute_live_job(job, root, out_folder, log):
        # As the live job does when the scan is complete before its first fit: the scan is reconstructed from
        # scratch, and the report has no `live` section (follow waits for the replay to end after it).
        return {"chamfer_mm": 3.0}

    monkeypatch.setattr(refits.live_job, "execute_live_job", execute_live_job)
    assert call(refits, ["--scene", "sphere", "--views", 2, "--every-s", 0.01, "--out", out]) == 1
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    assert "nothing measured for former, today" in captured.err.strip().splitlines()[-1]
    rows = [line for line in captured.out.splitlines() if line.startswith(("former", "today"))]
    assert len(rows) == 2 and all("the scan completed before the live fit started" in r for r in rows), rows
    assert [r["nothing_measured"] for r in json.loads((out / "refits.json").read_text())] == [refits.NOT_LIVE] * 2
