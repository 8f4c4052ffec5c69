"""Progress where standard error is not a terminal (`2>run.log`, cron, systemd, a pipe): no carriage-return frames of
a bar unless --progress asks for the bar. `spadscan reconstruct` then says its progress in plain lines, a few per run;
`simulate` and `import-lcspc` say nothing until their closing lines. A worker's job still writes the bar into its log,
where `spadscan worker --status`, the dashboard and the demo read it (worker/job_progress.py)."""

from __future__ import annotations

import inspect
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from spadscan.cli import main, progress_bar_wanted
from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.worker.children import spawn_job
from spadscan.worker.job_progress import claim_log, parse_progress, read_progress
from spadscan.worker.jobs import Job
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.trainer import LINE_EVERY_S, PROGRESS_LINES, train

HERE = Path(__file__).resolve().parent
RECON = "test_progress_not_a_terminal:trained_recon"


class Falling:
    """A stand-in model whose loss keeps falling; with `clock`, each step takes `step_s` of it (seconds)."""

    def __init__(self, clock: list[float] | None = None, step_s: float = 1.0):
        self.steps, self.clock, self.step_s = 0, clock, step_s

    def step(self) -> dict:
        self.steps += 1
        if self.clock is not None:
            self.clock[0] += self.step_s
        return {"loss": 1.0 / self.steps}


def trained_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                  started=None):
    """A job's reconstruction as the worker's job process calls it (no word about progress): the real training
    loop with its own default, on a stand-in model."""
    train(Falling(), RunPlan(steps=steps, budget_s=None, seed=seed), desc=f"reconstruct ({preset})")
    report = {"preset": preset, "steps": steps}
    (Path(out) / "report.json").write_text(json.dumps(report))
    return report


def fake_clock_lines(capsys, budget_s: float, step_s: float) -> list[str]:
    """The lines a run of `budget_s` seconds of steps of `step_s` (a fake clock) says with PROGRESS_LINES."""
    now = [0.0]
    train(Falling(now, step_s), RunPlan(steps=None, budget_s=budget_s, seed=0), progress=PROGRESS_LINES,
          clock=lambda: now[0], cpu_clock=lambda: now[0], desc="reconstruct (fast)")
    err = capsys.readouterr().err
    assert "\r" not in err and err.endswith("\n"), repr(err)
    return err.splitlines()


def test_progress_lines_come_at_each_tenth_of_the_training(capsys):
    lines = fake_clock_lines(capsys, budget_s=20.0, step_s=1.0)
    assert [line.split(",")[0] for line in lines] == \
        [f"reconstruct (fast): {s}.0/20.0 s of training ({5 * s} %)" for s in range(2, 21, 2)]
    assert lines[-1].endswith("[00:20]") and ", step 20, loss 0.05, ended budget " in lines[-1], lines[-1]


def test_progress_lines_of_a_long_run_come_at_least_every_30_s(capsys):
    lines = fake_clock_lines(capsys, budget_s=600.0, step_s=7.0)
    seconds = [int(line.split(": ")[1].split("/")[0]) for line in lines]  # whole seconds: a total of 100 s or more
    assert all(gap <= LINE_EVERY_S + 7 for gap in np.diff([0] + seconds)), seconds  # the first step past 30 s
    assert all(any(60 * k <= s < 60 * k + 7 for s in seconds) for k in range(1, 11)), "each tenth said"
    assert len(lines) < 600 / 7 / 3 and seconds[-1] == 600, seconds


def test_a_step_count_is_said_in_steps(capsys):
    train(Falling(), RunPlan(steps=30, budget_s=None, seed=0), progress=PROGRESS_LINES, desc="reconstruct (paper)")
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 10 and lines[-1].startswith("reconstruct (paper): 30/30 steps (100 %), step 30, loss "), lines


def test_a_run_that_ends_on_a_checkpoint_says_its_end_once_with_the_last_chamfer(capsys):
    """The last step reaches 100 %, then its checkpoint scores a new Chamfer. Before: a line at the last step (the
    Chamfer of the checkpoint before) and a second 100 % line from close(), with the new one."""
    scored = iter([10.0, 5.0, 3.0])
    train(Falling(), RunPlan(steps=10, budget_s=None, seed=0), progress=PROGRESS_LINES, checkpoints=2,
          evaluate=lambda: {"chamfer_mm": next(scored)}, desc="reconstruct (fast)")
    lines = capsys.readouterr().err.splitlines()
    ends = [line for line in lines if "(100 %)" in line]
    assert len(ends) == 1 and ends[0] == lines[-1], lines
    assert ", chamfer 3.00mm, scored at step 10, ended steps " in ends[0], ends[0]
    assert len(lines) == 10, "a line at each tenth, the last one the end's"


def test_a_reader_that_went_away_does_not_end_the_training():
    """`spadscan reconstruct ... 2>&1 | head -3`: the pipe closes after the first lines; the run goes on to its
    result. Before: the next line raised BrokenPipeError and the run was lost."""
    from spadscan.worker.recon.trainer import ProgressLines

    read, write = os.pipe()
    os.close(read)
    gone = os.fdopen(write, "w")
    lines = ProgressLines(10.0, "reconstruct (fast)", "step", clock=lambda: 0.0, file=gone)
    for _ in range(10):
        lines.update(1)
    lines.close()
    assert lines.n == 10 and lines.file is None
    try:
        gone.close()  # its buffer still holds the line that could not go: the closing flush fails as well
    except BrokenPipeError:
        pass


def test_a_budget_that_set_up_all_but_spent_is_said_in_hundredths(capsys):
    fake_clock_lines(capsys, budget_s=0.05, step_s=0.01)  # asserts its own shape
    train(Falling(), RunPlan(steps=None, budget_s=0.05, seed=0), progress=PROGRESS_LINES, desc="reconstruct (fast)")
    last = capsys.readouterr().err.splitlines()[-1]
    assert "/0.05 s of training" in last, last


STAND_IN = """
import sys, types
from pathlib import Path
from spadscan.cli import main
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.trainer import train

class Falling:
    steps = 0
    def step(self):
        self.steps += 1
        return {"loss": 1.0 / self.steps}

def stand_in(capture, out_dir, progress=True, **kwargs):  # the CLI's reconstruction, torch left out
    train(Falling(), RunPlan(steps=50, budget_s=None, seed=0), progress=progress, desc="reconstruct (fast)")
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    (Path(out_dir) / "mesh.ply").write_text("mesh")
    (Path(out_dir) / "report.json").write_text("{}")
    return {"preset": "fast", "steps": 50, "seconds": 1.0, "wall_seconds": 1.5, "device": "cpu", "converged": False,
            "final_loss": 0.02, "files": ["mesh.ply", "report.json"]}

module = types.ModuleType("spadscan.worker.reconstruct")
module.reconstruct_capture = stand_in
sys.modules["spadscan.worker.reconstruct"] = module
sys.exit(main(sys.argv[1:]))
"""


def reconstruct_into_a_file(tmp_path: Path, *flags: str) -> str:
    """`spadscan reconstruct` (its training a stand-in's) run with `flags`, stderr to a file: that file's text."""
    (tmp_path / "s").mkdir(exist_ok=True)
    (tmp_path / "s" / "scan.json").write_text("{}")  # a capture folder to the early check; the run a stand-in
    log = tmp_path / "run.log"
    with open(log, "w") as err:
        done = subprocess.run([sys.executable, "-c", STAND_IN, "reconstruct", str(tmp_path / "s"), "--out",
                               str(tmp_path / f"out{len(list(tmp_path.iterdir()))}"), "--no-gt", *flags],
                              stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=err, text=True, timeout=120)
    text = log.read_bytes().decode()  # as written: read_text() would read each carriage return as a newline
    assert done.returncode == 0, text
    return text


def test_reconstruct_writes_plain_lines_into_a_log_file(tmp_path):
    text = reconstruct_into_a_file(tmp_path)
    assert "\r" not in text, "no frames of a bar"
    said = [line for line in text.splitlines() if line.startswith("reconstruct (fast): ")]
    assert len(said) == 10 and said[-1].startswith("reconstruct (fast): 50/50 steps (100 %), step 50, loss 0.02"), text
    assert parse_progress(text) is None, "no bar for a bar's reader to take for a job's"


def test_reconstruct_whose_stderr_reader_is_gone_still_publishes_its_result(tmp_path):
    """Standard error a pipe no one reads any more (`2>&1 | head -3` after its lines): every line the run says
    fails, and the run still ends with its result. Before: the first progress line ended it, nothing published."""
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "scan.json").write_text("{}")  # a capture folder to the early check; the run a stand-in
    read, write = os.pipe()
    os.close(read)  # the reader is gone before the run says anything
    try:
        done = subprocess.run([sys.executable, "-c", STAND_IN, "reconstruct", str(tmp_path / "s"), "--out",
                               str(tmp_path / "out"), "--no-gt"], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                              stderr=write, text=True, timeout=120)
    finally:
        os.close(write)
    assert done.returncode == 0 and (tmp_path / "out" / "report.json").is_file(), done.stdout
    assert "wrote " in done.stdout


def test_reconstruct_draws_the_bar_into_a_file_when_asked_and_nothing_with_no_progress(tmp_path):
    bar = reconstruct_into_a_file(tmp_path, "--progress")
    assert "\r" in bar and parse_progress(bar).done == 50
    quiet = reconstruct_into_a_file(tmp_path, "--no-progress")
    assert "reconstruct (fast)" not in quiet and "\r" not in quiet, quiet


def test_a_workers_job_log_still_carries_the_bar_the_status_reads(tmp_path, arun):
    """The worker starts a job's process (children.spawn_job) with its output into its log, a file: the job's
    reconstruction, called without a word about progress, still draws the bar there, and job_progress reads it."""
    from spadscan.worker.reconstruct import reconstruct_capture

    assert inspect.signature(reconstruct_capture).parameters["progress"].default is True, \
        "a job's reconstruction is called with its default: the bar"
    root = tmp_path / "captures"
    sensor = sensor_preset("lcspc-sim")
    writer = CaptureWriter.create(root / "s", sensor, chunk_size=4)
    rng = np.random.default_rng(0)
    for i in range(2):  # background counts: a capture a job accepts
        writer.append(Measurement(rng.poisson(2.0, (1, sensor.n_bins)).astype(np.uint32), np.eye(4), i))
    writer.finish("complete")
    log = claim_log(root / ".queue", Path("s-fast~claim.json"))
    log.parent.mkdir(parents=True)
    env = {"PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])}

    async def job() -> int:
        proc = await spawn_job(Job(id="s-fast", scan="s", steps=20), root, tmp_path / "scratch", tmp_path / "outcome",
                               log, recon=RECON, extra_env=env)
        return await proc.wait()

    assert arun(job()) == 0, log.read_text()
    progress = read_progress(log)
    assert progress is not None, log.read_text()
    assert (progress.desc, progress.done, progress.total, progress.unit) == ("reconstruct (fast)", 20, 20, "step")
    assert progress.fields["step"] == "20"


def test_simulate_into_a_pipe_shows_no_bar_and_no_blank_line(tmp_path, capsys):
    assert main(["simulate", "builtin:sphere", "--views", "4", "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err and "%|" not in err, repr(err)
    assert err.startswith("wrote 4 views"), repr(err)
    assert main(["simulate", "builtin:sphere", "--views", "4", "--out", str(tmp_path / "b"), "--progress"]) == 0
    assert "simulate:" in capsys.readouterr().err, "the bar, asked for"


def look_at(k: int, n: int) -> list[list[float]]:
    """Pose k of n on a ring 0.5 m from the origin, its +z looking at it."""
    az = 2 * math.pi * k / n
    pos = 0.5 * np.array([math.cos(az) * 0.8, math.sin(az) * 0.8, 0.6])
    z = -pos / np.linalg.norm(pos)
    x = np.cross([0, 0, 1.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    pose[:3, 3] = pos
    return pose.tolist()


def test_import_lcspc_draws_its_bars_into_a_pipe_only_when_asked(tmp_path, capsys):
    rng = np.random.default_rng(0)
    src = tmp_path / "scene.json"
    src.write_text(json.dumps([{"hists": rng.integers(0, 400, 1024).tolist(), "pose": look_at(k, 4)}
                               for k in range(4)]))
    assert main(["import-lcspc", str(src), "--out", str(tmp_path / "a")]) == 0
    assert "%|" not in capsys.readouterr().err
    assert main(["import-lcspc", str(src), "--out", str(tmp_path / "b"), "--progress"]) == 0
    assert "%|" in capsys.readouterr().err


def test_the_bar_is_wanted_on_a_terminal_unless_refused():
    class Stream:
        def __init__(self, tty):
            self.tty = tty

        def isatty(self):
            return self.tty

    def args(**flags):
        return type("Args", (), {"progress": False, "no_progress": False, **flags})()

    assert progress_bar_wanted(args(), Stream(True)) and not progress_bar_wanted(args(), Stream(False))
    assert progress_bar_wanted(args(progress=True), Stream(False))
    assert not progress_bar_wanted(args(no_progress=True), Stream(True))
    closed = open(os.devnull)
    closed.close()
    assert not progress_bar_wanted(args(), closed), "a closed stream is no terminal"


def test_help_says_the_bars_seconds_are_trainings_share_of_the_budget(capsys):
    try:
        main(["reconstruct", "--help"])
    except SystemExit:
        pass
    text = " ".join(capsys.readouterr().out.split())
    assert "its seconds are training's share of the budget" in text
    assert "the mesh, metrics and pictures after it" in text
    assert "plain lines instead" in text and "--progress" in text


def test_both_flags_together_are_refused(tmp_path, capsys):
    try:
        main(["simulate", "builtin:sphere", "--out", str(tmp_path / "x"), "--progress", "--no-progress"])
    except SystemExit as exc:
        assert exc.code == 2
    else:
        raise AssertionError("accepted")
    assert "not allowed with argument" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
