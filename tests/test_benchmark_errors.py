"""The benchmark scripts' command lines: bad input is a one-line error, never a traceback; the options do what their
help says (metrics_speed's --repeats, the default output folders named and kept out of git); sweep_overhead counts
the cluster's shutdown apart from the points."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest
import torch

from benchmark_helpers import BENCHMARKS, load_benchmark


def call(bench, argv) -> tuple[int, str]:
    """(exit status, what it said on stderr) of a benchmark's main(argv), run in this process."""
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            code = bench.main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code
            if isinstance(code, str):  # SystemExit("message"): Python prints it and exits 1
                print(code, file=err)
                code = 1
    return code, err.getvalue()


def one_line(err: str) -> str:
    """The error line of what a script said (argparse puts its usage above it); fails on a traceback."""
    assert "Traceback" not in err, err
    return err.strip().splitlines()[-1]


def failed_run(stderr: str):
    """A stand-in for subprocess.run whose child fails, saying `stderr`."""
    def run(cmd, *args, **kwargs):
        return subprocess.CompletedProcess(cmd, 1, stdout="", stderr=stderr)
    return run


BAD = {
    "contention: a capture that does not read": (
        "contention", ["--capture", "{capture}", "--budget-s", 2, "--busy", 0],
        "spadscan: error: {capture}/scan.json: unreadable JSON", "failed: spadscan: error: "),
    "daemon_overhead: no frames": ("daemon_overhead", ["--dir", "{tmp}", "--frames", 0], None, "must be >= 1"),
    "daemon_overhead: no poses": ("daemon_overhead", ["--dir", "{tmp}", "--poses", 0], None, "must be >= 1"),
    "sweep_overhead: workers not a number": ("sweep_overhead", ["--skip-sweep", "--workers", "x"], None,
                                             "'x' must be comma-separated worker counts"),
    "sweep_overhead: no no-op points": ("sweep_overhead", ["--skip-sweep", "--noop-points", 0], None,
                                        "--noop-points 0 must be >= 1"),
    "sweep_overhead: no such sweep": ("sweep_overhead", ["--sweep", "{tmp}/no-such.toml"], None,
                                      "no-such.toml: no such sweep file"),
    "metrics_speed: no points": ("metrics_speed", ["--points", 0], None, "--points must be in [1, "),
    "metrics_speed: no repeats": ("metrics_speed", ["--points", 2000, "--repeats", 0], None, "--repeats >= 1"),
    "live_refits: no such scene": ("live_refits", ["--scene", "no-such-scene", "--out", "{tmp}/r"], None,
                                   "unknown scene 'no-such-scene'"),
    "live_refits: simulation fails": ("live_refits", ["--scene", "sphere", "--out", "{tmp}/r"],
                                      "spadscan: error: out of disk", "simulating builtin:sphere failed: spadscan"),
    "live_recoarse: no such scene": ("live_recoarse", ["--scenes", "no-such-scene", "--captures", "{tmp}/c"], None,
                                     "no built-in scene no-such-scene"),
    "live_recoarse: no scene": ("live_recoarse", ["--scenes", ",", "--captures", "{tmp}/c"], None,
                                "names no scene"),
    "live_recoarse: simulation fails": ("live_recoarse", ["--scenes", "mug", "--captures", "{tmp}/c"],
                                        "spadscan: error: out of disk", "simulating builtin:mug failed: spadscan"),
    "live: no scene": ("live", ["--scenes", ",", "--out", "{tmp}/l"], None, "--scenes ',' names no scene"),
    # 0 once ran the daemon's default of 128 views
    "live: no views": ("live", ["--scenes", "demo", "--views", 0, "--out", "{tmp}/l"], None,
                       "--views 0 must be an integer in [1, 10000]"),
    "make_scenes: a file as --out": ("make_scenes", ["--out", "{capture}/scan.json", "--groups", "table"], None,
                                     "scan.json: exists and is not a folder"),
    "warm_start_resampling: no steps": ("warm_start_resampling", ["{capture}", "--steps", 0, "--rebuilds", 1], None,
                                        "--steps and --rebuilds must be >= 1"),
    "warm_start_resampling: no rebuilds": ("warm_start_resampling", ["{capture}", "--steps", 20, "--rebuilds", 0],
                                           None, "--steps and --rebuilds must be >= 1"),
}


def no_runs(cmd, *args, **kwargs):
    raise AssertionError(f"a run started: {cmd}")


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_is_a_one_line_error(case, tmp_path, monkeypatch):
    stem, argv, child_says, message = BAD[case]
    capture = tmp_path / "capture"
    capture.mkdir()
    (capture / "scan.json").write_text("garbage")
    argv = [str(a).format(tmp=tmp_path, capture=capture) for a in argv]
    bench = load_benchmark(stem)
    # A child process that fails says so in its last line on stderr; where none should start, none may.
    monkeypatch.setattr(subprocess, "run",
                        no_runs if child_says is None else failed_run(child_says.format(capture=capture)))
    # What a script sets for its whole process is not set for the tests after this one.
    monkeypatch.setattr(signal, "signal", lambda signum, handler: signal.getsignal(signum))
    monkeypatch.setattr(torch, "set_num_threads", lambda n: None)
    code, err = call(bench, argv)
    assert code in (1, 2), err
    line = one_line(err)
    assert message in line, err
    if child_says is None:
        assert not (tmp_path / "l").exists() and not (tmp_path / "c").exists()  # nothing made before the error


def test_daemon_overhead_leaves_no_temporary_folder_when_it_fails(tmp_path, monkeypatch):
    bench = load_benchmark("daemon_overhead")

    async def failing_scan(*args, **kwargs):
        from spadscan.protocol.errors import ConfigError

        raise ConfigError("the scan could not start")

    monkeypatch.setattr(bench, "run_scan", failing_scan)
    code, err = call(bench, ["--dir", tmp_path / "d", "--poses", 3, "--frames", 8])
    assert code == 1 and "daemon_overhead.py: error: the scan could not start" in one_line(err)
    assert list((tmp_path / "d").iterdir()) == []  # its temporary captures removed


def test_metrics_speeds_repeats_count_for_mesh_metrics_too(monkeypatch, capsys):
    bench = load_benchmark("metrics_speed")
    asked = []

    def timed(fn, repeats):  # the figures are not the point here: run once, note the repeats asked for
        asked.append(repeats)
        return 0.0, fn()

    monkeypatch.setattr(bench, "timed", timed)
    assert bench.main(["--points", "2000", "--repeats", "3"]) in (0, None)
    assert asked and set(asked) == {3}, asked  # nearest_samples, cKDTree and both mesh_metrics, every case
    assert "equal" in capsys.readouterr().out


def test_sweep_overheads_per_point_figure_leaves_the_clusters_shutdown_out(monkeypatch, tmp_path):
    """The cluster's close (a second or more, whatever the points) is timed apart from the points: here a close that
    takes 0.5 s, on a stand-in for run_sweep that opens and closes the runner's client as run_sweep does."""
    bench = load_benchmark("sweep_overhead")
    from spadscan.sweep import runner

    class Summary:
        startup_s, failed = 0.0, []

    def enter(self):
        return self

    def slow_close(self, *exc):
        time.sleep(0.5)
        return False

    def fake_run_sweep(plan, out, workers, progress, **kwargs):
        with runner._client(None, workers, "cpu", None):
            time.sleep(0.1)  # the points
        return Summary()

    monkeypatch.setattr(runner._client, "__enter__", enter)
    monkeypatch.setattr(runner._client, "__exit__", slow_close)
    monkeypatch.setattr(bench, "run_sweep", fake_run_sweep)
    wall, startup, shutdown, failed = bench.on_dask(None, tmp_path, 1)
    assert shutdown >= 0.5 and wall - startup - shutdown < 0.5
    assert runner._client.__exit__ is slow_close  # put back as it was


@pytest.mark.parametrize("stem, default", [("error_vs_time", "benchmark-out"), ("next_best_view", "benchmark-nbv"),
                                           ("live_recoarse", "captures-live-recoarse")])
def test_a_default_output_folder_in_the_current_folder_is_named_in_help_and_ignored_by_git(stem, default, capsys):
    with pytest.raises(SystemExit):
        load_benchmark(stem).main(["--help"])
    assert f"default: {default}" in " ".join(capsys.readouterr().out.split())
    # Run from the repository's root, as RESULTS.md runs them, what they write stays out of `git status`.
    root = BENCHMARKS.parent
    for where in (Path(default) / "results.json", Path("benchmarks") / default / "results.json"):
        assert git_ignores(root, where), f"{where} is not ignored"


def git_ignores(root: Path, path: Path) -> bool:
    """Whether the ignore rules of the git checkout `root` ignore `path` (relative to it); skips the test, saying
    why, where there is no git or no checkout. Any checkout's owner will do: git refuses one that belongs to another
    user (a CI container's root over a mounted checkout, exit 128 "dubious ownership") unless told it is safe, and
    only reading its rules is asked here."""
    if shutil.which("git") is None:
        pytest.skip("no git here to read the ignore rules with")
    if not (root / ".git").exists():
        pytest.skip(f"{root} is no git checkout (no .git): no ignore rules to read")
    said = subprocess.run(["git", "-c", "safe.directory=*", "check-ignore", "--no-index", "-q", str(path)],
                          cwd=root, capture_output=True, text=True, timeout=60)
    assert said.returncode in (0, 1), f"git check-ignore: exit {said.returncode}: {said.stderr.strip()}"
    return said.returncode == 0


@pytest.mark.skipif(os.geteuid() != 0, reason="only root can give a checkout away")
def test_the_ignore_rules_are_read_in_a_checkout_of_another_user(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("no git here to make a checkout with")
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True, timeout=60)
    (tmp_path / ".gitignore").write_text("out/\n")
    for path in [tmp_path, *tmp_path.rglob("*")]:
        os.chown(path, 65534, 65534, follow_symlinks=False)  # nobody's, as a mounted checkout is another user's
    assert git_ignores(tmp_path, Path("out") / "results.json")
    assert not git_ignores(tmp_path, Path("kept") / "results.json")


def test_contentions_budget_is_described_as_the_whole_run(capsys):
    with pytest.raises(SystemExit):
        load_benchmark("contention").main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "whole-run budget of each `spadscan reconstruct`" in text and "training seconds per run" not in text


def test_warm_start_resampling_says_in_one_line_why_a_fit_cannot_run(tmp_path, monkeypatch):
    bench = load_benchmark("warm_start_resampling")
    from spadscan.worker.recon.errors import ReconstructionError

    def set_up_run(*args, **kwargs):
        raise ReconstructionError("the capture's views hold no photons")

    (tmp_path / "capture").mkdir()
    (tmp_path / "capture" / "scan.json").write_text("{}")
    monkeypatch.setattr(bench, "ground_truth", lambda capture: object())
    monkeypatch.setattr(bench, "set_up_run", set_up_run)
    monkeypatch.setattr(torch, "set_num_threads", lambda n: None)
    code, err = call(bench, [tmp_path / "capture", "--steps", 5, "--rebuilds", 1])
    assert code == 1 and one_line(err) == "warm_start_resampling: error: the capture's views hold no photons"
