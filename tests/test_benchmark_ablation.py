"""benchmarks/ablation.py: a run in --out is reused only when it was made with this call's settings (any other is
refused in one line that says which), and Ctrl-C still writes the table of the runs that finished.

The runs themselves (child processes of minutes each) are stood in for by a fake `run_in_child`."""

from __future__ import annotations

import json

import pytest

from benchmark_helpers import load_benchmark, tiny_capture


@pytest.fixture(scope="module")
def ablation():
    return load_benchmark("ablation")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return tiny_capture(tmp_path_factory.mktemp("ablation"))


def call(ablation, argv) -> int:
    """main's exit status, whether it returns it or argparse exits."""
    try:
        return ablation.main([str(a) for a in argv])
    except SystemExit as exc:
        return exc.code


class FakeRuns:
    """Stands in for run_in_child: each run writes its file as the child would, settings included (parts `ran` ran
    on the scene); a variant in `interrupt` is a Ctrl-C."""

    def __init__(self, ablation, ran=("erosion",), interrupt=()):
        self.ablation, self.ran, self.interrupt, self.runs = ablation, ran, interrupt, []

    def __call__(self, capture, target, args, overrides):
        variant = target.stem.split("--", 1)[1]
        if variant in self.interrupt:
            raise KeyboardInterrupt
        self.runs.append(variant)
        res = {"steps": args.steps, "stopped_by": "steps", "chamfer_mm": 2.0 if variant == "all-parts" else 3.0,
               "normal_error_deg": 10.0, "overrides": overrides, "summary": {"parts": dict.fromkeys(self.ran)},
               "settings": self.ablation.settings_of(args.steps, args.seed, args.threads, args.points, args.device,
                                                     overrides)}
        target.write_text(json.dumps(res))
        return res


def test_runs_made_with_other_settings_are_refused_in_one_line(ablation, capture, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    first = FakeRuns(ablation)
    monkeypatch.setattr(ablation, "run_in_child", first)
    assert call(ablation, ["--scenes", capture, "--out", out, "--steps", 5, "--parts", "erosion"]) == 0
    assert first.runs == ["all-parts", "erosion"]
    capsys.readouterr()

    # The same settings: both runs reused, nothing runs.
    again = FakeRuns(ablation)
    monkeypatch.setattr(ablation, "run_in_child", again)
    assert call(ablation, ["--scenes", capture, "--out", out, "--steps", 5, "--parts", "erosion"]) == 0
    assert again.runs == []

    # Other settings: refused before any run, saying which file and which setting.
    for extra, says in ((["--steps", 40], "--steps 5, not 40"),
                        (["--steps", 5, "--seed", 3], "--seed 0, not 3"),
                        (["--steps", 5, "--points", 2000], "--points 300000, not 2000"),
                        (["--steps", 5, "--set", "early_stop=false"], "--set none, not early_stop=false")):
        capsys.readouterr()
        assert call(ablation, ["--scenes", capture, "--out", out, "--parts", "erosion", *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert "box--all-parts.json" in err and says in err and "--overwrite" in err, err
    assert again.runs == []

    # --overwrite starts afresh with the new settings.
    fresh = FakeRuns(ablation)
    monkeypatch.setattr(ablation, "run_in_child", fresh)
    assert call(ablation, ["--scenes", capture, "--out", out, "--steps", 40, "--parts", "erosion", "--overwrite"]) == 0
    assert fresh.runs == ["all-parts", "erosion"]
    assert json.loads((out / "runs" / "box--all-parts.json").read_text())["settings"]["steps"] == 40


def test_a_run_that_records_no_settings_is_refused(ablation, capture, tmp_path, monkeypatch, capsys):
    runs = tmp_path / "out" / "runs"
    runs.mkdir(parents=True)
    (runs / "box--all-parts.json").write_text(json.dumps({"steps": 5, "summary": {"parts": {}}}))
    monkeypatch.setattr(ablation, "run_in_child", FakeRuns(ablation))
    assert call(ablation, ["--scenes", capture, "--out", tmp_path / "out", "--steps", 5]) == 2
    assert "no settings recorded" in capsys.readouterr().err


def test_ctrl_c_writes_the_table_of_the_runs_finished(ablation, capture, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    runs = FakeRuns(ablation, ran=("erosion", "openings"), interrupt=("openings",))
    monkeypatch.setattr(ablation, "run_in_child", runs)
    assert call(ablation, ["--scenes", capture, "--out", out, "--steps", 5, "--parts", "erosion,openings"]) == 130
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err and "interrupted" in captured.err
    table = (out / "table.md").read_text()
    assert "| all parts | 2.00 |" in table and "| erosion | 3.00 (+1.00) |" in table
    assert "| openings | - |" in table  # interrupted: not run
    assert set(json.loads((out / "results.json").read_text())["box"]) >= {"all parts", "erosion"}
