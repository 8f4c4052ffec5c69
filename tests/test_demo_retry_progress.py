"""The demo's reconstruction bar follows a job the worker runs again: its process crashed, the worker claims it
again, and the next attempt's training starts from nothing, in a log of its own. The bar starts over for it, names
the attempt, and a line says why the last one ended; it neither stays at the last attempt's count until the new one
passes it, nor says "mesh, metrics, pictures, report" while the new attempt trains."""

from __future__ import annotations

import io

from tqdm import tqdm

import spadscan.demo as demo
from spadscan.worker.job_progress import claim_log
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue

FIRST = "reconstruct (fast): 100%|##########| 8/8 s [00:08<00:00, step=216, loss=0.6]"
SECOND = "reconstruct (fast):  43%|####      | 3/7 s [00:03<00:04, step=14, loss=5.19]"
SECOND_DONE = "reconstruct (fast): 100%|##########| 7/7 s [00:07<00:00, step=200, loss=0.61]"
CRASH = "job process died with signal 9 (SIGKILL)"


def _log(queue: Queue, claim, text: str) -> None:
    log = claim_log(queue.path, claim.path)
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text(text)


def _bar(desc="reconstruction (training s)"):
    return tqdm(total=20, desc=desc, file=io.StringIO(), bar_format="{desc}: {n:.0f}/{total:.0f} {postfix}")


def _crashed_once(captures):
    """A queue whose job's first attempt trained to its end and crashed; returns (queue, first claim)."""
    queue = Queue.for_root(captures)
    queue.enqueue(Job(id="scan-fast", scan="scan"))
    first = queue.claim()
    _log(queue, first, FIRST)
    return queue, first


def test_the_running_run_names_its_claim_its_attempt_and_why_the_last_one_ended(tmp_path):
    assert demo.running_job_run(tmp_path) is None, "no queue yet: nothing runs"
    queue, first = _crashed_once(tmp_path)
    run = demo.running_job_run(tmp_path)
    assert (run.job_id, run.claim, run.attempt, run.progress.done, run.last_error) == \
        ("scan-fast", first.token, 1, 8, None)
    queue.crash(first, CRASH)
    assert demo.running_job_run(tmp_path) is None, "queued again, not running yet"
    second = queue.claim()
    run = demo.running_job_run(tmp_path)
    assert (run.claim, run.attempt, run.progress, run.last_error) == (second.token, 2, None, CRASH)
    _log(queue, second, SECOND)
    assert demo.running_job_run(tmp_path).progress.done == 3
    assert demo.running_job_progress(tmp_path).done == 3


def test_the_bar_starts_over_for_the_next_attempt(tmp_path):
    queue, first = _crashed_once(tmp_path)
    bar, said = _bar(), []
    show = demo.ReconProgress(bar, say=said.append)
    show.follow(demo.running_job_run(tmp_path))
    assert (bar.n, bar.total, bar.desc) == (8, 8, demo.ReconProgress.AFTER)
    queue.crash(first, CRASH)
    second = queue.claim()
    _log(queue, second, SECOND)
    show.follow(demo.running_job_run(tmp_path))
    assert (bar.n, bar.total) == (3, 7), "the new attempt's count, not the last one's 8 frozen"
    assert bar.desc == "reconstruction (training s), attempt 2"
    assert bar.postfix == "step 14, loss 5.19"
    assert said == [f"reconstruction job scan-fast: the worker runs it again, attempt 2 (the last attempt: {CRASH})"]
    _log(queue, second, SECOND_DONE)
    show.follow(demo.running_job_run(tmp_path))
    assert (bar.n, bar.desc) == (7, demo.ReconProgress.AFTER + ", attempt 2")
    assert len(said) == 1, "one line per attempt, not per look"
    bar.close()


def test_a_first_look_at_a_later_attempt_names_it():
    # The first attempt crashed before the demo's first look at it (during its set-up, say).
    bar, said = _bar(), []
    demo.ReconProgress(bar, say=said.append).follow(demo.JobRun("scan-fast", "c2", 2, None, CRASH))
    assert bar.desc == "reconstruction (training s), attempt 2" and len(said) == 1


def test_a_claim_given_back_and_claimed_again_is_a_run_again_of_the_same_attempt():
    bar = _bar()
    show = demo.ReconProgress(bar)
    show.follow(demo.JobRun("scan-fast", "c1", 1, None))
    assert bar.desc == "reconstruction (training s)", "a first attempt is not named"
    show.follow(demo.JobRun("scan-fast", "c2", 1, None))
    assert bar.desc == "reconstruction (training s), attempt 1, run again"


def test_the_published_runs_last_bar_goes_on_the_attempt_that_ran_it(tmp_path):
    # The job's result is published by its second attempt, which may have run from start to end between two looks.
    queue, first = _crashed_once(tmp_path)
    bar = _bar()
    show = demo.ReconProgress(bar)
    show.follow(demo.running_job_run(tmp_path))
    queue.crash(first, CRASH)
    second = queue.claim()
    result = tmp_path / "scan" / "recon" / "scan-fast"
    result.mkdir(parents=True)
    (result / "report.json").write_text("{}")
    (result / "job.log").write_text(SECOND_DONE + "\n")
    queue.record_result(second, str(result))
    queue.finish(second, str(result))
    run = demo.finished_job_run(tmp_path, "scan")
    assert (run.claim, run.attempt, run.progress.done) == (second.token, 2, 7)
    show.follow(run)
    assert (bar.n, bar.total, bar.desc) == (7, 7, demo.ReconProgress.AFTER + ", attempt 2")
    show.follow(run)
    assert bar.n == 7, "the same run again: nothing starts over"
    bar.close()


def test_an_earlier_scans_bar_starts_over_for_its_jobs_next_attempt(tmp_path):
    queue, first = _crashed_once(tmp_path)
    made, said = [], []

    def factory(total, desc, unit):
        made.append(_bar(desc))
        return made[-1]

    bars = demo.EarlierBars(tmp_path, factory, 20.0, said.append)
    bars()
    queue.crash(first, CRASH)
    second = queue.claim()
    _log(queue, second, SECOND)
    bars()
    assert len(made) == 1, "the same job keeps its bar"
    assert (made[0].n, made[0].total, made[0].desc) == (3, 7, "earlier scan scan (training s), attempt 2")
    assert len(said) == 1
    bars.close()
