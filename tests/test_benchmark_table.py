"""benchmarks/error_vs_time.py's table and plot: the columns it prints and their units, the marks it accepts, the
overrides it passes on, and the plot's tick labels."""

from __future__ import annotations

import argparse

import pytest



def run(trace, final, kind="preset"):
    """A result as run_preset writes it: trace entries of (wall seconds, Chamfer mm)."""
    return {"scene": "bunny", "method": "fast", "kind": kind, "stopped_by": "budget", "peak_rss_mb": 2000.0,
            "final_chamfer_mm": final, "trace": [{"wall_seconds": t, "chamfer_mm": c} for t, c in trace]}


def test_marks_are_columns_and_the_budget_mark_shows_the_final_checkpoint(bench):
    # Set-up took 2.8 s; the last step overran the 20 s budget by 0.04 s.
    result = run([(2.8, 22.4), (4.8, 2.91), (6.8, 1.89), (10.8, 1.91), (20.04, 1.58)], 1.58)
    text = bench.table([result], 20.0, (5.0, 10.0, 20.0, 30.0))
    head, _, row = text.splitlines()
    assert [c.strip() for c in head.strip("|").split("|")][2:5] == ["mm @5 s", "mm @10 s", "mm @20 s"]  # 30 > 20 s
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:6] == ["2.91", "1.89", "1.58", "1.58"]
    assert cells[7] == "6.80 s"  # the first checkpoint at or under 2 mm


def test_every_figure_column_names_its_unit(bench):
    text = bench.table([run([(2.8, 22.4), (20.0, 1.58)], 1.58)], 60.0, (30.0, 60.0))
    head, rule, row = text.splitlines()
    cells = [c.strip() for c in head.strip("|").split("|")]
    assert cells == ["scene", "method", "mm @30 s", "mm @60 s", "final mm", "ended", "to 2 mm", "peak MB"]
    assert [c.strip() for c in row.strip("|").split("|")] == ["bunny", "fast", "1.58", "1.58", "1.58", "budget",
                                                               "20.00 s", "2000"]
    assert set(rule) == {"|", "-"}


def test_a_mark_before_the_first_checkpoint_is_a_dash(bench):
    text = bench.table([run([(16.2, 44.2), (20.0, 5.01)], 5.01)], 20.0, (5.0, 10.0, 20.0))
    cells = [c.strip() for c in text.splitlines()[2].strip("|").split("|")]
    assert cells[2:5] == ["-", "-", "5.01"]
    assert cells[7] == "-"  # never under 2 mm


def test_marks_must_be_positive_finite_and_increasing(bench):
    assert bench.parse_marks("5,10,30") == (5.0, 10.0, 30.0)
    assert bench.parse_marks("2.5") == (2.5,)
    for bad in ("", "10,5", "5,5", "0,5", "-1", "inf", "nan", "five"):
        with pytest.raises(argparse.ArgumentTypeError):
            bench.parse_marks(bad)


def test_bad_marks_are_a_one_line_usage_error(bench, capsys):
    with pytest.raises(SystemExit) as exc:
        bench.main(["--scenes", "x", "--budget-s", "10", "--marks", "10,5"])
    assert exc.value.code == 2
    assert "marks must be positive, finite and increasing" in capsys.readouterr().err


def test_overrides_reach_the_preset_config_and_bad_keys_are_refused(bench, tmp_path):
    from spadscan.protocol.errors import SpadscanError

    with pytest.raises(SpadscanError, match="no_such_field"):
        bench.run_preset(tmp_path, "fast", 1.0, 1.0, "cpu", 0, tmp_path, overrides=["schedule.no_such_field=1"])


class StoppedModel:
    """Steps that take no time until the n-th, which is interrupted (as a time limit or Ctrl-C would)."""

    def __init__(self, n: int):
        self.n, self.steps = n, 0

    def step(self):
        self.steps += 1
        if self.steps >= self.n:
            raise KeyboardInterrupt
        return {"loss": 1.0 / self.steps}


def test_a_run_killed_mid_way_leaves_its_checkpoints_for_the_table(bench, tmp_path):
    from spadscan.worker.recon.model_api import RunPlan
    from spadscan.worker.recon.trainer import train

    partial = bench.partial_path(tmp_path / "bunny-fast.json")
    keep = bench.partial_writer(partial, "fast", "cpu", setup_s=3.0,
                                provenance={"commit": "abc123", "config": {"preset": "fast"}})
    chamfers = iter([20.0, 5.0, 2.5, 1.9])
    with pytest.raises(KeyboardInterrupt):
        # The product's trainer, as run_preset calls it; every_s=0: a checkpoint at the start and after every step,
        # so the 4th step is interrupted after the 4th checkpoint.
        train(StoppedModel(4), RunPlan(steps=None, budget_s=100.0, seed=0), every_s=0.0,
              evaluate=lambda: {"chamfer_mm": next(chamfers)}, scoring_in_budget=False, on_checkpoint=keep,
              progress=False)
    res = bench.cut_off_result(partial)
    assert [e["chamfer_mm"] for e in res["trace"]] == [20.0, 5.0, 2.5, 1.9]
    assert all(e["wall_seconds"] >= 3.0 for e in res["trace"])  # set-up counts
    assert res["final_chamfer_mm"] == 1.9 and res["peak_rss_mb"] is None
    assert (res["commit"], res["config"]) == ("abc123", {"preset": "fast"})  # every figure says what made it
    # The checkpoints come right after the 3 s of set-up (the steps take no time, but a busy machine still takes
    # some between them): the table read at the last one's time shows it.
    last_s = res["trace"][-1]["wall_seconds"]
    assert last_s < 30.0
    cells = [c.strip() for c in bench.table([{**res, "scene": "bunny"}], 100.0, (last_s, 30.0)).splitlines()[2]
             .strip("|").split("|")]
    # At the last checkpoint: its figure; at 30 s, after the run was cut off: nothing is known.
    assert cells[2:5] == ["1.90", "-", "1.90"]
    assert cells[5].startswith("cut off") and cells[7] == "-"  # peak memory unknown


def test_the_commit_names_uncommitted_changes(bench, monkeypatch):
    import subprocess

    answers = {"rev-parse": "0123abcd\n", "status": ""}

    def fake(cmd, **kwargs):
        return answers[cmd[3]]

    monkeypatch.setattr(bench.subprocess, "check_output", fake)
    assert bench.source_commit() == "0123abcd"
    answers["status"] = " M worker/recon/fast/model.py\n"
    assert bench.source_commit() == "0123abcd + uncommitted changes"

    def no_git(cmd, **kwargs):
        raise subprocess.CalledProcessError(128, cmd)

    monkeypatch.setattr(bench.subprocess, "check_output", no_git)
    assert bench.source_commit() == "unknown"


def test_no_partial_or_an_empty_one_is_no_result(bench, tmp_path):
    assert bench.cut_off_result(tmp_path / "missing.partial.json") is None
    (tmp_path / "half.partial.json").write_text('{"trace": [')  # never written by write_atomic, but be safe
    assert bench.cut_off_result(tmp_path / "half.partial.json") is None
    bench.write_atomic(tmp_path / "empty.partial.json", {"trace": []})
    assert bench.cut_off_result(tmp_path / "empty.partial.json") is None


def test_the_method_peak_memory_leaves_the_scoring_of_checkpoints_out(bench):
    import numpy as np
    import torch

    meter = bench.MethodPeak(torch.device("cpu"))
    if not meter.excludes_scoring:
        pytest.skip("this system cannot reset a process's peak memory (/proc/self/clear_refs)")
    base_mb = bench._hwm_kb() / 1024
    method = np.ones(200 * 2**20 // 8)  # 200 MB, touched by the method
    del method
    meter.pause()
    scoring = np.ones(600 * 2**20 // 8)  # 600 MB, touched while a checkpoint is scored
    del scoring
    meter.resume()
    peak = meter.peak_mb()
    assert base_mb + 150 < peak < base_mb + 450
    assert meter.peak_with_scoring_mb() > base_mb + 550  # what the whole process took, scoring included


def result(scene, points, kind="preset", method="fast"):
    return {"scene": scene, "method": method, "kind": kind,
            "trace": [{"wall_seconds": t, "chamfer_mm": c} for t, c in points]}


def tick_labels(fig) -> list[str]:
    """The tick labels drawn inside each axis's view."""
    fig.canvas.draw()
    labels = []
    for ax in fig.axes:
        for axis, (lo, hi) in ((ax.xaxis, ax.get_xlim()), (ax.yaxis, ax.get_ylim())):
            for ticks, locs in ((axis.get_majorticklabels(), axis.get_majorticklocs()),
                                (axis.get_minorticklabels(), axis.get_minorticklocs())):
                labels += [t.get_text() for t, v in zip(ticks, locs) if t.get_text() and lo <= v <= hi]
    return labels


def test_log_axes_are_labelled_with_plain_numbers(bench):
    import matplotlib.pyplot as plt

    # Less than a decade on both axes of the sphere (minor ticks get labels), three decades on the bunny's.
    fig = bench.figure([result("sphere", [(2.8, 24.3), (4.7, 4.29)]),
                        result("bunny", [(1.0, 100.0), (30.0, 2.0), (600.0, 0.5)]),
                        result("bunny", [(3.0, 16.6)], kind="baseline", method="space-carving")])
    labels = tick_labels(fig)
    plt.close(fig)
    assert {"3", "4", "20", "1", "10", "100"} <= set(labels)
    for text in labels:
        assert text == f"{float(text):g}", text  # '20', never '2 x 10^1' or '$\\mathdefault{...}$'


def test_no_plot_without_a_chamfer(bench, tmp_path):
    path = tmp_path / "error_vs_time.png"
    assert bench.plot([], path) is False and not path.exists()
    assert bench.plot([result("bunny", [(3.0, None)])], path) is False and not path.exists()
    assert bench.plot([result("bunny", [(3.0, None)]), result("soap", [(3.0, 4.0)])], path) and path.is_file()
