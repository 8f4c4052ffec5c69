"""`spadscan sweep` and `spadscan demo` with standard error in a file or a pipe (here: pytest's capture, which is no
terminal): no carriage-return frames of a bar unless --progress asks for the bars. The sweep then says a line per
finished point, as with --no-progress; the demo says each bar as plain lines (ProgressLines), its end once."""

from __future__ import annotations

import functools

import pytest

import spadscan.cli as cli
import spadscan.demo as demo
from spadscan.cli import main
from spadscan.sweep import runner
from spadscan.worker.job_progress import parse_progress

SWEEP = """
[sweep]
scenes = ["builtin:sphere"]

[base]
views = 8

[grid]
views = [8, 12]
"""
"""Two points: the base condition and views=12."""


def point_done(task, out, device, keep):
    """A point that is done at once, with a result per method (the sweep's own simulate and reconstruct skipped)."""
    return {"id": task.id, "status": "done", "reason": None, "seconds": 0.0, "worker": None,
            "methods": {"fast": {"status": "done", "chamfer_mm": 5.2194, "warnings": 0},
                        "reprojection": {"status": "done", "chamfer_mm": 22.03, "warnings": 0},
                        "space-carving": {"status": "done", "chamfer_mm": 30.1, "warnings": 0}}}


@pytest.fixture
def sweep_on_a_cluster(tmp_path, monkeypatch):
    """`spadscan sweep FILE --out DIR --scheduler ADDRESS *flags` on an in-process cluster, its points `point_done`:
    returns a function of (out folder name, *flags) that runs it and returns its stderr."""
    from distributed import LocalCluster

    sweep = tmp_path / "sweep.toml"
    sweep.write_text(SWEEP)
    monkeypatch.setattr(runner, "run_sweep", functools.partial(runner.run_sweep, point=point_done))
    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None,
                           protocol="tcp://", host="127.0.0.1")  # an address the command takes

    def run(capsys, name: str, *flags: str) -> str:
        assert main(["sweep", str(sweep), "--out", str(tmp_path / name), "--scheduler", cluster.scheduler_address,
                     *flags]) == 0
        captured = capsys.readouterr()
        assert "2 points: 0 done earlier, 2 run now (2 done, 0 failed)" in captured.out, captured
        return captured.err

    try:
        yield run
    finally:
        cluster.close()


def point_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("spadscan sweep: point ")]


def test_a_sweep_into_a_file_says_a_line_per_point_not_the_bar(sweep_on_a_cluster, capsys):
    err = sweep_on_a_cluster(capsys, "default")
    assert "\r" not in err and "%|" not in err, repr(err)
    lines = point_lines(err)
    assert sorted(line.split()[3] for line in lines) == ["1/2", "2/2"], err
    assert all(line.endswith(": done; fast 5.22 mm, reprojection 22 mm, space-carving 30.1 mm") for line in lines)
    quiet = point_lines(sweep_on_a_cluster(capsys, "quiet", "--no-progress"))
    assert points_said(quiet) == points_said(lines), "the lines of --no-progress"


def points_said(lines: list[str]) -> list[str]:
    """The lines without their place in the order the points finished in ('point 1/2')."""
    return sorted(line.split(" ", 4)[4] for line in lines)


def test_a_sweep_draws_the_bar_into_a_file_when_asked_and_on_a_terminal(sweep_on_a_cluster, capsys, monkeypatch):
    err = sweep_on_a_cluster(capsys, "asked", "--progress")
    assert "\r" in err and "sweep: 100%|" in err and not point_lines(err), repr(err)
    monkeypatch.setattr(cli, "is_terminal", lambda stream: True)
    err = sweep_on_a_cluster(capsys, "terminal")
    assert "sweep: 100%|" in err and not point_lines(err), repr(err)
    assert len(point_lines(sweep_on_a_cluster(capsys, "terminal-quiet", "--no-progress"))) == 2, "--no-progress kept"


def test_the_sweeps_help_names_both_flags(capsys):
    with pytest.raises(SystemExit):
        main(["sweep", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--progress draw the progress bar even when standard error is not a terminal" in text
    assert "a line per finished point, as with --no-progress" in text
    assert "--no-progress no progress bar: a line on standard error per finished point instead" in text


RUN_1 = "reconstruct (fast): 100%|##########| 8/8 s [00:08<00:00, step=216, loss=0.6]"
RUN_2 = ["reconstruct (fast):  43%|####      | 3/7 s [00:03<00:04, step=14, loss=5.19]",
         "reconstruct (fast): 100%|##########| 7/7 s [00:07<00:00, step=200, loss=0.61, chamfer=1.21mm, "
         "scored=at step 200]"]


JOB_FINISHED = "(the job finished)"
"""What fake_run_demo says once the job it follows has finished, before it closes the bar."""


def fake_run_demo(opts, bar, say):
    """What run_demo asks of its bars, without the daemon and the worker: the scan's bar counts poses and shows the
    live fit (LiveWatch), set after the count; the reconstruction's bar follows a job (ReconProgress) that crashes
    and runs again from nothing."""
    scan = bar(opts.views, "scan (poses)", "pose")
    for pose in range(1, opts.views + 1):
        scan.update(1)
        scan.set_postfix_str(f"live: {pose}/{pose} views, {10 * pose} steps")
    scan.close()
    recon = bar(opts.budget_s, "final reconstruction (training s)", "s")
    show = demo.ReconProgress(recon, say=say)
    show.follow(demo.JobRun("scan-fast", "claim-1", 1, parse_progress(RUN_1)))
    for line in RUN_2:
        show.follow(demo.JobRun("scan-fast", "claim-2", 2, parse_progress(line), "job process died with signal 9"))
    say(JOB_FINISHED)  # the job's mesh, metrics, pictures and report are made before this
    recon.close()
    return {"mesh": str(opts.out / "mesh.ply"), "warnings": [], "converged": True, "pictures": [], "live": None,
            "chamfer_mm": 1.21, "seconds": {"start_s": 0.1, "scan_s": 1.0, "reconstruct_s": 2.0, "total_s": 3.1},
            "preset": "fast", "report_html": str(opts.out / "report.html"), "dashboard": None}


def run_fake_demo(tmp_path, monkeypatch, capsys, *flags: str):
    """`spadscan demo --views 20 *flags` on fake_run_demo: (stdout, stderr)."""
    monkeypatch.setattr(demo, "run_demo", fake_run_demo)
    assert main(["demo", "--out", str(tmp_path / "out"), "--views", "20", *flags]) == 0
    captured = capsys.readouterr()
    assert "chamfer:  1.21 mm" in captured.out and "report:" in captured.out, "the summary, whatever the flags"
    return captured.out, captured.err


def test_a_demo_into_a_file_says_its_bars_as_lines_each_end_once(tmp_path, monkeypatch, capsys):
    _, err = run_fake_demo(tmp_path, monkeypatch, capsys)
    assert "\r" not in err and "%|" not in err, repr(err)
    scan = [line for line in err.splitlines() if line.startswith("scan (poses): ")]
    assert [line.split(",")[0] for line in scan] == [f"scan (poses): {2 * k}/20 poses ({10 * k} %)"
                                                     for k in range(1, 11)], err
    assert scan[-1].startswith("scan (poses): 20/20 poses (100 %), live: 20/20 views, 200 steps ["), \
        "the end once, with the fields set after its count"
    # Its seconds as reconstruct says them where checkpoint scoring counts in the budget (a demo's scene has a
    # ground truth).
    recon = [line for line in err.splitlines() if "reconstruction" in line and "s of training" in line]
    after = demo.ReconProgress.AFTER
    assert [line.split(" [")[0] for line in recon] == [
        # the crashed attempt's end, before its retry
        f"{after}: 8.0/8.0 s of training and checkpoint scoring (100 %), step 216, loss 0.6",
        "final reconstruction (training s), attempt 2: 3.0/7.0 s of training and checkpoint scoring (43 %), step 14, "
        "loss 5.19",
        f"{after}, attempt 2: 7.0/7.0 s of training and checkpoint scoring (100 %), step 200, loss 0.61, "
        "checkpoint Chamfer 1.21 mm (step 200)",
    ], err
    said = err.splitlines()
    assert said.index(recon[0]) < said.index(next(line for line in said if "runs it again" in line)) < \
        said.index(recon[1]), "the retry said between its attempts' lines"
    assert said.index(recon[-1]) < said.index(JOB_FINISHED), "the end's stage said as it starts, not after it"
    assert "reconstruction job scan-fast: the worker runs it again, attempt 2" in err


def test_a_demo_with_no_progress_shows_no_bar_and_no_line(tmp_path, monkeypatch, capsys):
    _, err = run_fake_demo(tmp_path, monkeypatch, capsys, "--no-progress")
    assert "scan (poses)" not in err and "reconstruction (training s)" not in err and "\r" not in err, err
    assert "reconstruction job scan-fast: the worker runs it again" in err, "what happens is still said"


def test_a_demo_draws_its_bars_into_a_file_when_asked_and_on_a_terminal(tmp_path, monkeypatch, capsys):
    _, err = run_fake_demo(tmp_path, monkeypatch, capsys, "--progress")
    assert "\r" in err and "scan (poses): 100%|" in err, repr(err)
    monkeypatch.setattr(cli, "is_terminal", lambda stream: True)
    _, err = run_fake_demo(tmp_path, monkeypatch, capsys)
    assert "scan (poses): 100%|" in err and "poses (100 %)" not in err, repr(err)


def test_the_demos_help_names_both_flags(capsys):
    with pytest.raises(SystemExit):
        main(["demo", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--progress draw the progress bars even when standard error is not a terminal (default: the bars" in text
    assert "--no-progress draw no progress bars and write no progress lines" in text


def test_both_flags_together_are_refused(tmp_path, capsys):
    for command in (["demo"], ["sweep", str(tmp_path / "sweep.toml")]):
        with pytest.raises(SystemExit) as exc:
            main([*command, "--out", str(tmp_path / "out"), "--progress", "--no-progress"])
        assert exc.value.code == 2 and "not allowed with argument" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_demos_bar_interface_is_what_run_demo_asks_of_it():
    """run_demo's bars: update, close, total (read and set to a job's own), desc, set_postfix_str,
    set_description_str and reset (ReconProgress and LiveWatch ask with hasattr: a missing one is silently not
    shown)."""
    from spadscan.worker.recon.trainer import ProgressLines

    lines = ProgressLines(10.0, "d", "s", clock=lambda: 0.0, file=None)
    for name in ("update", "close", "set_postfix_str", "set_description_str", "reset"):
        assert callable(getattr(lines, name)), name
    lines.update(4)
    lines.total = 8.0
    assert (lines.n, lines.total, lines.step, lines.desc) == (4, 8.0, 0.8, "d")
    lines.reset()
    assert (lines.n, lines.total) == (0, 8.0)


def test_a_new_description_at_the_end_of_the_count_is_said_at_once():
    """The demo's end stage ("mesh, metrics, pictures, report") comes after the count's end: said as it starts,
    once, not at close() after the stage (a log silent through it, its line dated after it)."""
    import io

    from spadscan.worker.recon.trainer import ProgressLines

    file = io.StringIO()
    lines = ProgressLines(10.0, "training", "s", clock=lambda: 0.0, file=file)
    lines.set_description_str("training, attempt 2")  # before the end: said with the next count
    assert file.getvalue() == ""
    lines.update(10.0)
    assert file.getvalue() == "", "the end of the count is close()'s, or the stage's after it"
    lines.set_description_str("mesh, metrics, pictures, report")
    assert file.getvalue().splitlines() == ["mesh, metrics, pictures, report: 10.0/10.0 s of training (100 %) [00:00]"]
    lines.set_description_str("mesh, metrics, pictures, report")
    lines.close()
    assert len(file.getvalue().splitlines()) == 1, "said once"
