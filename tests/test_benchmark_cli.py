"""benchmarks/error_vs_time.py's command line: every option checked before the first run, one line per problem, an
--out holding an earlier run refused unless --overwrite, and runs that fail never crash the table or the plot.

The runs themselves (child processes of several seconds each) are stood in for by a fake `subprocess.run`."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

REAL_RUN = subprocess.run
"""subprocess.run before a test stands in for it (the benchmark's git queries still run)."""


def simulated_box(folder: Path, views: int, rays_per_zone: int) -> Path:
    """A capture of a box seen from `views` simulated views at 0.3 m."""
    import trimesh

    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    mesh = trimesh.creation.box(extents=(0.07, 0.05, 0.09))
    mesh.apply_translation([0.0, 0.0, 0.045])
    poses = fibonacci_hemisphere(views, 0.3, target=(0, 0, 0.05), min_elevation_deg=15)
    return simulate_capture(mesh, sensor_preset("lcspc-sim"), poses, folder / "box",
                            settings=SimSettings(rays_per_zone=rays_per_zone), progress=False)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """Two simulated views of a box: a capture that reads (the runs never start on it here)."""
    return simulated_box(tmp_path_factory.mktemp("bench"), 2, 64)


def call(bench, argv) -> int:
    """main's exit status, whether it returns it or argparse exits."""
    try:
        return bench.main([str(a) for a in argv])
    except SystemExit as exc:
        return exc.code


class FakeRuns:
    """Stands in for subprocess.run of the child processes: each run ends with `returncode`, and a successful one
    writes a result as run_preset would (two checkpoints, 20 mm at 2 s and 1.5 mm at 4 s)."""

    def __init__(self, returncode: int = 0):
        self.returncode, self.runs = returncode, []

    def __call__(self, cmd, *args, **kwargs):
        if cmd[0] == "git":  # the benchmark asks which commit it measures
            return REAL_RUN(cmd, *args, **kwargs)
        assert "--one" in cmd
        method, result = cmd[-2], Path(cmd[-1])
        self.runs.append(method)
        if self.returncode == 0:
            result.write_text(json.dumps({
                "method": method, "kind": "preset", "stopped_by": "budget", "final_chamfer_mm": 1.5,
                "peak_rss_mb": 500.0, "trace": [{"wall_seconds": 2.0, "chamfer_mm": 20.0},
                                                {"wall_seconds": 4.0, "chamfer_mm": 1.5}]}))
        return subprocess.CompletedProcess(cmd, self.returncode)


def no_runs(cmd, *args, **kwargs):
    if cmd[0] == "git":
        return REAL_RUN(cmd, *args, **kwargs)
    raise AssertionError(f"a run started: {cmd}")


def bad_capture(root: Path) -> Path:
    (root / "broken").mkdir()
    (root / "broken" / "scan.json").write_text('{"format": "something else"}')
    return root / "broken"


def empty_capture(root: Path, capture: Path) -> Path:
    """A capture whose manifest reads but that holds no views."""
    (root / "empty").mkdir()
    (root / "empty" / "scan.json").write_text((capture / "scan.json").read_text())
    return root / "empty"


def missing_ground_truth(root: Path, capture: Path) -> Path:
    (root / "nogt").mkdir()
    manifest = json.loads((capture / "scan.json").read_text())
    manifest["scene"] = {"ground_truth": str(root / "gone.obj")}
    (root / "nogt" / "scan.json").write_text(json.dumps(manifest))
    for chunk in capture.glob("chunk-*"):
        (root / "nogt" / chunk.name).symlink_to(chunk)
    return root / "nogt"


def offset_scene(root: Path, capture: Path) -> Path:
    """The capture as if of the built-in sphere placed 10 cm off (mesh_offset_m, as the daemon's simulated sensor
    records it)."""
    (root / "offset").mkdir()
    manifest = json.loads((capture / "scan.json").read_text())
    manifest["scene"] = {"builtin": "sphere", "mesh_offset_m": [0.1, 0.0, 0.0]}
    (root / "offset" / "scan.json").write_text(json.dumps(manifest))
    for chunk in capture.glob("chunk-*"):
        (root / "offset" / chunk.name).symlink_to(chunk)
    return root / "offset"


BAD = {
    "unknown preset": (["--presets", "foo"], "unknown preset 'foo' (known: paper, fast)"),
    "no preset, no baselines": (["--presets", ""], "nothing to run: --presets is empty and --baselines is not given"),
    "a preset twice": (["--presets", "fast,fast"], "'fast' is named twice"),
    "a baseline as a preset": (["--presets", "reprojection"], "'reprojection' is a baseline"),
    "an override without =": (["--set", "nokey"], "'nokey' must look like KEY=VALUE"),
    "an override of no field": (["--set", "schedule.no_such_field=1"], "preset 'fast'"),
    "an override of the wrong type": (["--set", "mesh_resolution=fine"], "mesh_resolution 'fine' must be an integer"),
    "an override and no preset": (["--presets", "", "--baselines", "--set", "mesh_resolution=64"],
                                  "no preset is run"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_options_are_one_line_errors_before_any_run(bench, capture, tmp_path, monkeypatch, capsys, case):
    monkeypatch.setattr(bench.subprocess, "run", no_runs)
    extra, message = BAD[case]
    out = tmp_path / "out"
    assert call(bench, ["--scenes", capture, "--budget-s", 5, "--out", out, *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and "Traceback" not in err
    assert not out.exists()  # nothing written, nothing imported


def test_every_bad_scene_is_named_in_its_own_line(bench, capture, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bench.subprocess, "run", no_runs)
    (tmp_path / "a_file").write_text("")
    (tmp_path / "nothing").mkdir()
    scenes = [tmp_path / "gone", tmp_path / "a_file", tmp_path / "nothing", bad_capture(tmp_path),
              empty_capture(tmp_path, capture), missing_ground_truth(tmp_path, capture),
              offset_scene(tmp_path, capture), capture, capture]
    assert call(bench, ["--scenes", *scenes, "--budget-s", 5, "--presets", "foo", "--out", tmp_path / "out"]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 9 and all(line.startswith("error_vs_time.py: error: ") for line in lines)
    text = "\n".join(lines)
    # A scene placed with an offset was scored against its mesh where it did not stand (a perfect fit: 50 mm).
    for expected in ("gone: no such folder", "a_file: not a folder", "nothing: holds neither scan.json",
                     "not a spadscan capture", "empty: the capture holds no views", "gone.obj: no such ground-truth",
                     "stood offset by mesh_offset_m [0.1, 0.0, 0.0]", f"scene {capture} is named twice",
                     "unknown preset 'foo'"):
        assert expected in text


@pytest.mark.parametrize("extra, message", [
    (["--budget-s", "nan"], "--budget-s: 'nan' must be a positive, finite number of seconds"),
    (["--budget-s", "0"], "--budget-s: '0' must be a positive"),
    (["--budget-s", "inf"], "--budget-s: 'inf' must be a positive"),
    (["--budget-s", "5", "--every-s", "-1"], "--every-s: '-1' must be a positive"),
    (["--budget-s", "5", "--seed", "-1"], "--seed: '-1' must be an integer >= 0"),
    (["--budget-s", "5", "--eval-resolution", "0"], "--eval-resolution: '0' must be an integer >= 2"),
    (["--budget-s", "5", "--marks", "10,5"], "marks must be positive, finite and increasing"),
])
def test_bad_numbers_are_one_line_usage_errors(bench, capture, tmp_path, monkeypatch, capsys, extra, message):
    monkeypatch.setattr(bench.subprocess, "run", no_runs)
    assert call(bench, ["--scenes", capture, "--out", tmp_path / "out", *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err


def test_when_every_run_fails_the_table_still_comes_out_without_a_plot(bench, capture, tmp_path, monkeypatch,
                                                                      capsys):
    runs = FakeRuns(returncode=1)
    monkeypatch.setattr(bench.subprocess, "run", runs)
    out = tmp_path / "out"
    assert call(bench, ["--scenes", capture, "--budget-s", 5, "--presets", "fast,paper", "--out", out]) == 1
    assert runs.runs == ["fast", "paper"]
    captured = capsys.readouterr()
    assert "| scene | method | final mm | ended           | to 2 mm | peak MB |" in captured.out
    # Each failed run is a row that says so, with no figure (it left no checkpoint).
    assert "| box   | fast   | -        | failed (exit 1) | -       | -       |" in captured.out
    assert "| box   | paper  | -        | failed (exit 1) | -       | -       |" in captured.out
    assert "no plot: every run failed" in captured.err
    assert "2 of 2 runs failed: box fast (exit 1), box paper (exit 1)" in captured.err
    assert "Traceback" not in captured.err
    assert [(r["method"], r["failed"], r["final_chamfer_mm"], r["trace"])
            for r in json.loads((out / "results.json").read_text())["results"]] == [
        ("fast", "exit 1", None, []), ("paper", "exit 1", None, [])]
    assert (out / "table.md").is_file() and not (out / "error_vs_time.png").exists()


class DiesAfterTwoCheckpoints:
    """Stands in for subprocess.run of a child that wrote two checkpoints (56.18 mm at 2 s, 7.63 mm at 3 s of wall
    time, 1 s of it set-up) to its partial file, then ended as `how` says: 'SIGKILL' (by another hand, as the OOM
    killer does: exit -9) or 'interrupt' (Ctrl-C or SIGTERM to the benchmark: subprocess.run raises
    KeyboardInterrupt)."""

    def __init__(self, bench, how: str):
        self.bench, self.how = bench, how

    def __call__(self, cmd, *args, **kwargs):
        if cmd[0] == "git":
            return REAL_RUN(cmd, *args, **kwargs)
        keep = self.bench.partial_writer(self.bench.partial_path(Path(cmd[-1])), cmd[-2], "cpu", setup_s=1.0)
        keep([{"seconds": 1.0, "step": 4, "chamfer_mm": 56.18}, {"seconds": 2.0, "step": 9, "chamfer_mm": 7.63}])
        if self.how == "interrupt":
            raise KeyboardInterrupt
        return subprocess.CompletedProcess(cmd, -9)


def row_of(out: str, method: str) -> list[str]:
    return next([c.strip() for c in line.strip("|").split("|")] for line in out.splitlines()
                if line.startswith("| box ") and f" {method} " in line)


def test_a_run_killed_by_another_hand_is_failed_not_a_final_figure(bench, capture, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bench.subprocess, "run", DiesAfterTwoCheckpoints(bench, "SIGKILL"))
    out = tmp_path / "out"
    assert call(bench, ["--scenes", capture, "--budget-s", 10, "--every-s", 1, "--marks", "2,4,8", "--out", out]) == 1
    captured = capsys.readouterr()
    assert "box: fast failed (exit -9)" in captured.err and "1 of 1 runs failed: box fast (exit -9)" in captured.err
    # Its checkpoints stay at the marks they reached; no final figure, and "failed", not "cut off".
    assert row_of(captured.out, "fast") == ["box", "fast", "56.18", "-", "-", "-", "failed (exit -9)", "-", "-"]
    (res,) = json.loads((out / "results.json").read_text())["results"]
    assert res["failed"] == "exit -9" and res["stopped_by"] == "failed"  # not "cut off", as its partial file said
    assert res["final_chamfer_mm"] is None and res["peak_rss_mb"] is None
    assert [e["chamfer_mm"] for e in res["trace"]] == [56.18, 7.63]
    assert (out / "table.md").read_text().count("failed (exit -9)") == 1


def test_a_run_cut_off_by_ctrl_c_is_cut_off_not_failed(bench, capture, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bench.subprocess, "run", DiesAfterTwoCheckpoints(bench, "interrupt"))
    out = tmp_path / "out"
    call(bench, ["--scenes", capture, "--budget-s", 10, "--every-s", 1, "--marks", "2,4,8", "--out", out])
    captured = capsys.readouterr()
    assert "interrupted" in captured.err and "failed" not in captured.err
    assert row_of(captured.out, "fast") == ["box", "fast", "56.18", "-", "-", "7.63", "cut off 3 s", "-", "-"]
    (res,) = json.loads((out / "results.json").read_text())["results"]
    assert "failed" not in res and res["stopped_by"] == "cut off"


def test_an_earlier_run_in_out_is_refused_unless_overwrite(bench, capture, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    argv = ["--scenes", capture, "--budget-s", 5, "--out", out, "--presets", "fast,paper"]
    monkeypatch.setattr(bench.subprocess, "run", FakeRuns())
    assert call(bench, argv) == 0
    assert {p.name for p in (out / "runs").iterdir()} == {"box-fast.json", "box-paper.json"}
    assert (out / "error_vs_time.png").is_file()
    capsys.readouterr()

    # The same --out again, with `fast` alone: refused, and nothing of the earlier run is touched.
    monkeypatch.setattr(bench.subprocess, "run", no_runs)
    assert call(bench, argv[:-1] + ["fast"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "already holds an earlier run" in err and "--overwrite" in err
    assert (out / "runs" / "box-paper.json").is_file()

    # With --overwrite the earlier run's files go first: no stale box-paper.json beside this run's box-fast.json.
    runs = FakeRuns()
    monkeypatch.setattr(bench.subprocess, "run", runs)
    assert call(bench, argv[:-1] + ["fast", "--overwrite"]) == 0
    assert runs.runs == ["fast"]
    assert {p.name for p in (out / "runs").iterdir()} == {"box-fast.json"}
    assert [r["method"] for r in json.loads((out / "results.json").read_text())["results"]] == ["fast"]
    assert "deleted the earlier run's" in capsys.readouterr().err


def test_an_out_that_is_a_file_is_refused(bench, capture, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bench.subprocess, "run", no_runs)
    (tmp_path / "out").write_text("")
    assert call(bench, ["--scenes", capture, "--budget-s", 5, "--out", tmp_path / "out", "--overwrite"]) == 2
    assert "exists and is not a folder" in capsys.readouterr().err


def test_a_run_that_fails_says_why_in_one_line(bench, capture, tmp_path, capsys):
    # The child process's side: a problem the checks could not foresee is one line, not a traceback.
    result = tmp_path / "box-fast.json"
    code = call(bench, ["--scenes", capture, "--budget-s", 1, "--set", "schedule.no_such_field=1",
                        "--one", capture, "fast", result])
    assert code == 1 and not result.exists()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: box: fast: ") and "no_such_field" in err


def test_a_dataset_folder_is_imported_again_when_its_file_changed(bench, tmp_path, monkeypatch):
    import spadscan.protocol.lcspc as lcspc

    imports = []

    def fake_import(source, cap):
        imports.append(Path(source).name)
        cap.mkdir(parents=True)
        (cap / "scan.json").write_text(json.dumps({"scene": {"source": str(Path(source).resolve())}}))

    monkeypatch.setattr(lcspc, "import_lcspc", fake_import)
    for name in ("one", "two"):
        (tmp_path / name / "sphere").mkdir(parents=True)
        (tmp_path / name / "sphere" / "sphere.json").write_text("{}")
    work = tmp_path / "out"
    first = bench.prepare_scene(tmp_path / "one" / "sphere", work)
    assert bench.prepare_scene(tmp_path / "one" / "sphere", work) == first  # imported once
    assert imports == ["sphere.json"]
    bench.prepare_scene(tmp_path / "two" / "sphere", work)  # another folder of the same name: not the cached import
    assert imports == ["sphere.json", "sphere.json"]
    assert bench.imported_from(first) == str((tmp_path / "two" / "sphere" / "sphere.json").resolve())
    # A capture there that is no dataset import (made or copied by someone) is never deleted.
    mine = work / "captures" / "mine"
    mine.mkdir(parents=True)
    (mine / "scan.json").write_text(json.dumps({"scene": {}}))
    (tmp_path / "three" / "mine").mkdir(parents=True)
    (tmp_path / "three" / "mine" / "mine.json").write_text("{}")
    with pytest.raises(SystemExit, match="holds a capture that is no dataset import"):
        bench.prepare_scene(tmp_path / "three" / "mine", work)
    assert (mine / "scan.json").is_file()


@pytest.fixture(scope="module")
def views_of_a_box(tmp_path_factory):
    """Twelve simulated views of a box: enough for the fast preset to carve a hull and train."""
    return simulated_box(tmp_path_factory.mktemp("bench"), 12, 256)


def test_a_preset_run_goes_through_the_products_trainer_and_records_its_commit_and_config(bench, views_of_a_box,
                                                                                         tmp_path):
    # The child process's side, for real: a tiny fast run of 2 s.
    capture = views_of_a_box
    result = tmp_path / "box-fast.json"
    small = ["field.resolution=12", "field.hull_resolution=24", "schedule.views_per_step=2",
             "schedule.rays_per_sr=200", "schedule.candidate_rays_per_sr=1000", "parts.openings.enabled=false"]
    argv = ["--scenes", capture, "--budget-s", 2, "--every-s", 0.5, "--device", "cpu"]
    argv += [x for kv in small for x in ("--set", kv)]
    assert call(bench, argv + ["--one", capture, "fast", result]) == 0
    res = json.loads(result.read_text())
    assert res["stopped_by"] in ("budget", "converged") and res["steps"] >= 1
    assert res["commit"] and res["config"]["preset"] == "fast"
    assert res["config"]["parts"]["openings"]["enabled"] is False and res["config"]["field"]["resolution"] == 12
    assert "openings" in res["summary"]["parts_left_out"]  # the run did what its config says
    walls = [e["wall_seconds"] for e in res["trace"]]
    assert walls == sorted(walls) and walls[0] == pytest.approx(res["setup_s"]) and len(walls) >= 2
    assert not bench.partial_path(result).exists()  # a finished run leaves no partial file


@pytest.mark.parametrize("stem, extra", [("error_vs_time", ["--scenes", "{capture}", "--budget-s", "5"]),
                                         ("ablation", ["--scenes", "{capture}"]),
                                         ("next_best_view", ["--scenes", "builtin:sphere"]), ("make_scenes", [])])
def test_an_out_that_cannot_be_made_is_refused_in_one_line(capture, tmp_path, capsys, stem, extra):
    """A place no one can write (/proc; root included): one line naming --out, before any run, no traceback."""
    from benchmark_helpers import load_benchmark

    argv = ["--out", "/proc/spadscan-test"] + [a.format(capture=capture) for a in extra]
    assert call(load_benchmark(stem), argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith("error: --out /proc/spadscan-test: cannot create it (No such file or directory)"), err
    assert not any("Traceback" in line for line in err)
