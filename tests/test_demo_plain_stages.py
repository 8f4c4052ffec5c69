"""A job's training that ends short of its count's total (a run that converged early, a budget whose last step left
part of a second of it) says so on its bar (`ended=...`), and what reads the bar from the job's log takes it for the
end of the training: `spadscan worker --status` and the demo's bar say the job's end stage ("mesh, metrics, pictures,
report") from then on, not only once its result is out.

In a file or a pipe (plain lines) the demo never said the end stage for such a run: the lines ended on the training's
last reading and the summary followed. On a terminal the bar kept its training description at 99 % while the job
made its mesh, metrics, pictures and report."""

from __future__ import annotations

import contextlib
import io

from tqdm import tqdm

import spadscan.demo as demo
from spadscan.cli import main
from spadscan.worker.job_progress import AFTER_TRAINING, claim_log, parse_progress
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.trainer import train

AFTER = demo.ReconProgress.AFTER


class ConvergesAtStep3:
    """A model whose third step reports it converged: a run of 10 steps ends at 3."""

    def __init__(self):
        self.steps = 0

    def step(self) -> dict:
        self.steps += 1
        return {"loss": 1.0 / self.steps, "converged": self.steps >= 3}


def converged_log() -> str:
    """What a job's log holds once the trainer's run that converged at step 3 of 10 has ended: its bar, as the
    trainer draws it into a file, and that bar closed."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        result = train(ConvergesAtStep3(), RunPlan(steps=10, budget_s=None), early_stop=True,
                       desc="reconstruct (fast)")
    assert (result.stopped_by, result.steps) == ("converged", 3)
    return err.getvalue()


CLOSED = converged_log()
TRAINING = CLOSED[:CLOSED.rindex("reconstruct (fast)")]
"""The same log while the run's steps are drawn, before its training ended."""


def running(tmp_path):
    """A queue whose job is running; returns a function that writes the running claim's log."""
    queue = Queue.for_root(tmp_path)
    queue.enqueue(Job(id="scan-fast", scan="scan"))
    claim = queue.claim()
    log = claim_log(queue.path, claim.path)
    log.parent.mkdir(parents=True, exist_ok=True)
    return log.write_text


def test_the_bar_of_a_training_that_ended_short_of_its_total_says_it_ended():
    assert "ended=converged" in CLOSED and "ended=" not in TRAINING, repr(CLOSED[-200:])
    during, after = parse_progress(TRAINING), parse_progress(CLOSED)
    assert (during.done, during.total, during.training_done) == (3, 10, False)
    assert (after.done, after.total, after.training_done) == (3, 10, True)
    assert AFTER_TRAINING in after.when() and AFTER_TRAINING not in during.when()


def test_the_running_run_is_read_as_its_log_shows_it(tmp_path):
    write = running(tmp_path)
    for text, over in ((TRAINING, False), (CLOSED, True)):
        write(text)
        progress = demo.running_job_run(tmp_path).progress
        assert (progress.done, progress.total, progress.training_done) == (3, 10, over), repr(text[-100:])


def test_a_terminal_bar_stopped_short_says_the_end_stage_at_its_count(tmp_path):
    write = running(tmp_path)
    bar = tqdm(total=120, desc="reconstruction (training s)", file=io.StringIO(),
               bar_format="{desc}: {n:.0f}/{total:.0f} {postfix}")
    show = demo.ReconProgress(bar)
    write(TRAINING)
    show.follow(demo.running_job_run(tmp_path))
    assert (bar.n, bar.total, bar.desc) == (3, 10, "reconstruction (training s)"), "still training"
    write(CLOSED)
    show.follow(demo.running_job_run(tmp_path))
    assert (bar.n, bar.total, bar.desc) == (3, 10, AFTER), "the end stage, at the count where training stopped"
    bar.close()


BUDGET_RUN = ["reconstruct (fast):  50%|#####     | 51/102 s [00:51<00:51, step=1240, loss=0.9]",
              "reconstruct (fast):  99%|#########9| 101/102 s [01:41<00:01, step=2480, loss=0.66]",
              "reconstruct (fast):  99%|#########9| 101/102 s [01:41<00:01, step=2480, loss=0.66, ended=budget]"]
"""A budget run's bar, look after look, whose last step left it one second short of its total, then its end."""
BLANKED = "\r" + " " * 80 + "\r"
"""What tqdm writes into the log where the trainer closes that bar."""
JOB_FINISHED = "(the job finished)"


def fake_run_demo(opts, bar, say):
    """run_demo's reconstruction stage, without the daemon and the worker: the bar follows the running job of a
    real queue, look after look at its log (BUDGET_RUN, its bar closed at the end), then the run that published it."""
    captures = opts.out / "captures"
    write = running(captures)
    recon = bar(opts.budget_s, "reconstruction (training s)", "s")
    show = demo.ReconProgress(recon, say=say)
    for looks in (1, 2, 3):
        look = "\r".join(BUDGET_RUN[:looks]) + (BLANKED if looks == 3 else "")
        write(look)
        show.follow(demo.running_job_run(captures))
    say(JOB_FINISHED)  # the job's mesh, metrics, pictures and report are made before this
    result = captures / "scan" / "recon" / "scan-fast"
    result.mkdir(parents=True)
    (result / "report.json").write_text("{}")
    (result / "job.log").write_text("\r".join(BUDGET_RUN) + BLANKED)
    show.follow(demo.finished_job_run(captures, "scan"))
    recon.close()
    return {"mesh": str(opts.out / "mesh.ply"), "warnings": [], "converged": True, "pictures": [], "live": None,
            "chamfer_mm": 1.21, "seconds": {"start_s": 0.1, "scan_s": 1.0, "reconstruct_s": 2.0, "total_s": 3.1},
            "preset": "fast", "report_html": str(opts.out / "report.html"), "dashboard": None}


def test_plain_lines_say_the_end_stage_of_a_run_stopped_short_of_its_total(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(demo, "run_demo", fake_run_demo)
    assert main(["demo", "--out", str(tmp_path / "out"), "--offline", "--budget-s", "120"]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err and "%|" not in err, repr(err)
    recon = [line.split(" [")[0] for line in err.splitlines() if "s of training" in line]
    assert recon == [
        "reconstruction (training s): 51/102 s of training and checkpoint scoring (50 %), step 1240, loss 0.9",
        "reconstruction (training s): 101/102 s of training and checkpoint scoring (99 %), step 2480, loss 0.66",
        f"{AFTER}: 101/102 s of training and checkpoint scoring (99 %), step 2480, loss 0.66",
    ], err
    assert err.count(AFTER) == 1, "said once"
    assert err.index(AFTER) < err.index(JOB_FINISHED), "said when the training ended, not once the job was over"
