"""benchmarks/ablation.py: a run in --out is reused only when it was made with this call's settings and scene folder
(any other is refused in one line that says which), Ctrl-C still writes the table of the runs that finished, and a
run that fails is "failed" in the table and the exit status, never a figure or "n/a".

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
    on the scene); a variant in `interrupt` is a Ctrl-C, one in `fail` fails as a child that exits 1 does."""

    def __init__(self, ablation, ran=("erosion",), interrupt=(), fail=()):
        self.ablation, self.ran, self.interrupt, self.fail, self.runs = ablation, ran, interrupt, fail, []

    def __call__(self, capture, target, args, overrides, scene, children=None):
        variant = target.stem.split("--", 1)[1]
        if variant in self.interrupt:
            raise KeyboardInterrupt
        self.runs.append(variant)
        if variant in self.fail:
            return {"failed": "RuntimeError: out of memory"}
        res = {"steps": args.steps, "stopped_by": "steps", "chamfer_mm": 2.0 if variant == "all-parts" else 3.0,
               "normal_error_deg": 10.0, "overrides": overrides, "summary": {"parts": dict.fromkeys(self.ran)},
               "settings": self.ablation.settings_of(scene, args.steps, args.seed, args.threads, args.points,
                                                     args.device, overrides)}
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


def rows_of(table: str) -> dict[str, list[str]]:
    """The first table's rows: part -> its cells."""
    first = table.split("### ")[1]
    return {r.strip("|").split("|")[0].strip(): [c.strip() for c in r.strip("|").split("|")[1:]]
            for r in first.splitlines() if r.startswith("| ") and not r.startswith("| part off")}


def test_a_failed_all_parts_run_is_failed_not_n_a_and_the_exit_status_is_1(ablation, capture, tmp_path,
                                                                           monkeypatch, capsys):
    out = tmp_path / "out"
    runs = FakeRuns(ablation, fail=("all-parts",))
    monkeypatch.setattr(ablation, "run_in_child", runs)
    assert call(ablation, ["--scenes", capture, "--out", out, "--steps", 5, "--parts", "erosion,openings"]) == 1
    captured = capsys.readouterr()
    assert "1 runs failed: box all parts (RuntimeError: out of memory)" in captured.err
    table = (out / "table.md").read_text()
    # Nothing is known of the parts: not "n/a" (that says the part does not run on the scene), not run.
    assert rows_of(table) == {"all parts": ["failed"], "erosion": ["-"], "openings": ["-"]}
    assert "| n/a |" not in table  # in none of the three tables
    assert runs.runs == ["all-parts"]
    assert json.loads((out / "results.json").read_text())["box"] == {"all parts": {
        "failed": "RuntimeError: out of memory"}}
    assert not (out / "runs" / "box--all-parts.json").exists()  # not kept: the same command runs it again

    again = FakeRuns(ablation)
    monkeypatch.setattr(ablation, "run_in_child", again)
    assert call(ablation, ["--scenes", capture, "--out", out, "--steps", 5, "--parts", "erosion,openings"]) == 0
    assert again.runs == ["all-parts", "erosion"]


def test_a_failed_ablation_is_failed_in_its_cell_and_the_exit_status_is_1(ablation, capture, tmp_path, monkeypatch,
                                                                         capsys):
    out = tmp_path / "out"
    monkeypatch.setattr(ablation, "run_in_child", FakeRuns(ablation, fail=("erosion",)))
    assert call(ablation, ["--scenes", capture, "--out", out, "--steps", 5, "--parts", "erosion"]) == 1
    assert "box erosion (RuntimeError: out of memory)" in capsys.readouterr().err
    assert rows_of((out / "table.md").read_text()) == {"all parts": ["2.00"], "erosion": ["failed"]}


def test_a_child_that_fails_gives_its_last_line_of_error(ablation, tmp_path):
    args = ablation.argparse.Namespace(steps=1, seed=0, threads=1, points=1000, device="cpu")
    target = tmp_path / "runs" / "missing--all-parts.json"
    res = ablation.run_in_child(tmp_path / "missing", target, args, [], str(tmp_path / "missing"))
    assert set(res) == {"failed"} and res["failed"], res
    assert not target.exists()


@pytest.mark.parametrize("shell, stopped", [("kill -INT $$", True), ("kill -TERM $$", True),
                                             ("echo broke >&2; exit 1", False)])
def test_a_child_ended_by_a_stop_signal_was_stopped_not_failed(ablation, tmp_path, shell, stopped):
    # A Ctrl-C that reaches a run between its fork and its own process group ends it before this script's own
    # KeyboardInterrupt has stopped the others: not run ("-", run again by the same command), never "failed".
    class ShellChildren(ablation.Children):
        def start(self, cmd, env):
            return super().start(["sh", "-c", shell], env)

    args = ablation.argparse.Namespace(steps=1, seed=0, threads=1, points=1000, device="cpu")
    target = tmp_path / "runs" / "box--all-parts.json"
    res = ablation.run_in_child(tmp_path / "box", target, args, [], "box", children=ShellChildren())
    assert res is None if stopped else res == {"failed": "broke"}, res


def test_cuda_without_a_cuda_device_is_refused_before_any_run(ablation, capture, tmp_path, monkeypatch, capsys):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    runs = FakeRuns(ablation)
    monkeypatch.setattr(ablation, "run_in_child", runs)
    assert call(ablation, ["--scenes", capture, "--out", tmp_path / "out", "--steps", 5, "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "no CUDA device" in err.strip().splitlines()[-1]
    assert runs.runs == [] and not (tmp_path / "out").exists()


def test_two_scene_folders_of_one_name_are_refused(ablation, capture, tmp_path, monkeypatch, capsys):
    other = tiny_capture(tmp_path / "v2")
    assert other.name == capture.name
    runs = FakeRuns(ablation)
    monkeypatch.setattr(ablation, "run_in_child", runs)
    assert call(ablation, ["--scenes", capture, other, "--out", tmp_path / "out", "--steps", 5]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "share the name 'box'" in err, err
    assert runs.runs == [] and not (tmp_path / "out").exists()


def test_a_run_made_from_another_scene_folder_of_the_same_name_is_refused_not_reused(ablation, capture, tmp_path,
                                                                                     monkeypatch, capsys):
    out = tmp_path / "out"
    other = tiny_capture(tmp_path / "v2")
    first = FakeRuns(ablation)
    monkeypatch.setattr(ablation, "run_in_child", first)
    assert call(ablation, ["--scenes", other, "--out", out, "--steps", 5, "--parts", "erosion"]) == 0
    assert json.loads((out / "runs" / "box--all-parts.json").read_text())["settings"]["scene"] == str(other.resolve())
    capsys.readouterr()

    again = FakeRuns(ablation)
    monkeypatch.setattr(ablation, "run_in_child", again)
    assert call(ablation, ["--scenes", capture, "--out", out, "--steps", 5, "--parts", "erosion"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"--scenes {other.resolve()}, not {capture.resolve()}" in err and "--overwrite" in err, err
    assert again.runs == []


def test_an_out_that_is_a_file_is_refused_before_any_run(ablation, capture, tmp_path, monkeypatch, capsys):
    (tmp_path / "afile").write_text("")
    runs = FakeRuns(ablation)
    monkeypatch.setattr(ablation, "run_in_child", runs)
    assert call(ablation, ["--scenes", capture, "--out", tmp_path / "afile", "--steps", 5]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "exists and is not a folder" in err.strip().splitlines()[-1]
    assert runs.runs == []


def test_a_run_is_scored_on_the_metrics_fixed_samples_whatever_its_seed(ablation, tmp_path, monkeypatch):
    """`spadscan reconstruct` scores every run on the metrics' own seed (0, docs/metrics.md): an ablation run of
    seed 3 is scored on the same samples, so that its figure is the project's figure of its mesh."""
    from spadscan.cli import main

    sphere = tmp_path / "sphere"
    assert main(["simulate", "builtin:sphere", "--views", "12", "--rays-per-zone", "64", "--out", str(sphere),
                 "--no-progress"]) == 0
    asked = []
    truth = ablation.ground_truth(sphere)

    class Recorded:
        def metrics(self, pred, **options):
            asked.append(options)
            return truth.metrics(pred, **options)

    monkeypatch.setattr(ablation, "ground_truth", lambda capture: Recorded())
    record = ablation.run_one(sphere, steps=2, seed=3, threads=1, overrides=[], points=2000)
    assert asked and all(options.get("seed", 0) == 0 for options in asked), asked
    assert record["chamfer_mm"] > 0
