"""A running job's progress as `spadscan worker --status` and the dashboard show it: its log's training bar, measured
against the job's own budget where it has one (set-up, training, mesh, metrics and pictures share it), so that the
bar is never full, "00:00 left", while the job still has its mesh, metrics and pictures to make."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from types import SimpleNamespace

import pytest

from spadscan.protocol.live_status import LiveStatus, write_status
from spadscan.worker import job_progress
from spadscan.worker.job_progress import (AFTER_TRAINING, LogTails, ProgressNote, ProgressNotes, progress_note,
                                          running_progress)
from spadscan.worker.jobs import Job
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

MID = "reconstruct (fast):  57%|#####     | 4/7 s [00:04<00:03, step=38, loss=851]\r"
FULL = "reconstruct (fast): 100%|##########| 7/7 s [00:07<00:00, step=67, loss=518]\r"


def running_job(root, bar: str, **job) -> tuple[Queue, float, Path]:
    """A queue under `root` with one claimed job whose log shows `bar`; returns (queue, its claim's start, the
    log)."""
    queue = Queue.for_root(root)
    queue.enqueue(Job(id="scan-fast", scan="scan", **job))
    claim = queue.claim()
    (queue.path / "logs").mkdir(exist_ok=True)
    log = queue.path / "logs" / f"{claim.path.stem}.log"
    log.write_text(bar)
    (record,) = queue.read_records("scan-fast")[0]
    return queue, record["started_unix"], log


def test_a_job_with_a_budget_whose_training_is_over_is_not_shown_as_done(tmp_path):
    queue, _, _ = running_job(tmp_path, MID + FULL, budget_s=600.0)  # claimed just now
    p = running_progress(queue)["scan-fast"]
    assert p.fraction < 0.5 and "00:00 left" not in p.line(), p.line()


def test_a_job_with_a_budget_is_shown_against_it_and_says_what_follows_its_training(tmp_path):
    queue, start, log = running_job(tmp_path, MID, budget_s=20.0)
    p = running_progress(queue, now=start + 9.0)["scan-fast"]
    assert p.fraction == pytest.approx(9 / 20)
    assert p.line() == "reconstruct (fast): 4/7 s, step 38, loss 851 [00:09 of the job's 00:20 budget, 00:11 left]"
    log.write_text(MID + FULL)
    p = running_progress(queue, now=start + 15.0)["scan-fast"]
    assert p.fraction == pytest.approx(0.75), "the training is over, the job is not"
    assert p.line().endswith("[training done: mesh, metrics, pictures; 00:15 of the job's 00:20 budget, 00:05 left]")
    assert (p.done, p.total) == (7, 7), "the training bar's own reading stays (the demo draws it)"
    late = running_progress(queue, now=start + 23.0)["scan-fast"]
    assert late.fraction == 1.0 and late.line().endswith("00:23 of the job's 00:20 budget, 00:03 over]")
    data = late.to_dict()
    assert (data["budget_s"], data["spent_s"], data["training_done"]) == (20.0, pytest.approx(23.0), True)


def test_a_live_jobs_budget_counts_from_its_scans_end_when_its_final_run_starts(tmp_path):
    queue, start, _ = running_job(tmp_path, FULL, budget_s=20.0, live=True)
    folder = tmp_path / "scan" / "recon" / "live"
    folder.mkdir(parents=True)
    ended = start + 100.0  # the scan ran for 100 s, the live job following it
    final = LiveStatus(views_used=24, views_published=24, steps=300, state="final", job="scan-fast",
                       updated_utc=_dt.datetime.fromtimestamp(ended, _dt.timezone.utc).isoformat())
    write_status(folder, final)
    p = running_progress(queue, now=ended + 12.0)["scan-fast"]
    assert p.fraction == pytest.approx(12 / 20)
    assert p.line().endswith("[training done: mesh, metrics, pictures; 00:12 of the job's 00:20 budget, 00:08 left]")
    write_status(folder, LiveStatus(views_used=24, views_published=24, steps=300, state="final", job="other-job",
                                    updated_utc=final.updated_utc))
    assert running_progress(queue, now=ended + 12.0)["scan-fast"].budget_s is None, "not its own status"


def test_a_full_training_bar_without_a_budget_says_what_the_job_does_next_not_00_00_left(tmp_path):
    queue, _, _ = running_job(tmp_path, MID + FULL)
    p = running_progress(queue)["scan-fast"]
    assert p.fraction == 1.0 and p.budget_s is None
    assert p.line() == ("reconstruct (fast): 7/7 s, step 67, loss 518 "
                        "[training done: mesh, metrics, pictures (training took 00:07)]")


def test_the_worker_says_a_job_at_each_change_of_stage_and_every_interval_between(tmp_path):
    """The worker's own terminal: a job's line when its stage changes and every `interval_s` seconds in between,
    never twice for one stage within the interval; set-up goes unsaid until the interval has passed (the 'started'
    line has just said it)."""
    notes = ProgressNotes(interval_s=30.0)
    setting_up, training, after = (ProgressNote(stage, stage) for stage in ("setting up", "training", AFTER_TRAINING))
    looks = [(0.0, setting_up), (29.0, setting_up), (31.0, setting_up), (32.0, training), (33.0, after),
             (34.0, training), (60.0, training), (64.0, training), (93.9, training), (94.0, training)]
    said = [now for now, note in looks if notes.due("claim", note, now=now)]
    assert said == [31.0, 32.0, 33.0, 34.0, 64.0, 94.0]
    notes.keep_only([])
    assert not notes.due("claim", setting_up, now=95.0), "a claim that ran again starts afresh"
    assert notes.due("claim", training, now=95.5)


def test_a_progress_note_says_the_bar_against_the_budget_else_the_live_status_else_that_it_sets_up(tmp_path):
    queue = Queue.for_root(tmp_path)
    queue.enqueue(Job(id="scan-fast", scan="scan", budget_s=120.0))
    queue.enqueue(Job(id="live-fast", scan="live", live=True))
    claims = {c.job.id: c for c in (queue.claim(), queue.claim())}
    logs = {job_id: tmp_path / f"{job_id}.log" for job_id in claims}
    ordinary, live = claims["scan-fast"], claims["live-fast"]
    note = progress_note(ordinary, logs["scan-fast"], tmp_path, now=ordinary.started + 12.0)
    assert note == ProgressNote("setting up", "scan-fast: setting up, no progress bar in its log yet "
                                              "[00:12 of the job's 02:00 budget, 01:48 left]")
    logs["scan-fast"].write_text(MID)
    note = progress_note(ordinary, logs["scan-fast"], tmp_path, now=ordinary.started + 48.0)
    assert note.stage == "reconstruct (fast): training"
    assert note.text == ("scan-fast at 40 %: reconstruct (fast): 4/7 s, step 38, loss 851 "
                         "[00:48 of the job's 02:00 budget, 01:12 left]")
    logs["scan-fast"].write_text(MID + FULL)
    note = progress_note(ordinary, logs["scan-fast"], tmp_path, now=ordinary.started + 60.0)
    assert note.stage == f"reconstruct (fast): {AFTER_TRAINING}" and note.text.startswith("scan-fast at 50 %: ")
    note = progress_note(live, logs["live-fast"], tmp_path, now=live.started + 5.0)
    assert note.text == "live-fast: setting up, no progress bar in its log yet [00:05 since it started]"
    (tmp_path / "live" / "recon" / "live").mkdir(parents=True)
    write_status(tmp_path / "live" / "recon" / "live", LiveStatus(views_used=24, views_published=29, steps=240,
                                                                  job="live-fast"))
    note = progress_note(live, logs["live-fast"], tmp_path)
    assert note.stage == "live: live" and note.text.startswith("live-fast: live reconstruction following the scan: "
                                                               "24/29 views, 240 steps"), note


def count_reads(monkeypatch) -> list[Path]:
    """The logs `read_progress` reads from now on, one entry a read."""
    reads: list[Path] = []
    read = job_progress.read_progress

    def counted(log, *args, **kwargs):
        reads.append(Path(log))
        return read(log, *args, **kwargs)

    monkeypatch.setattr(job_progress, "read_progress", counted)
    return reads


def test_the_worker_reads_a_jobs_log_again_only_once_it_has_changed(tmp_path, monkeypatch):
    """The worker looks at its running jobs at every turn of its loop; a log's tail (16 KB) is read again only when
    the log has changed, and the lines said are those a fresh reading gives."""
    worker = Worker(WorkerConfig(root=tmp_path), log=lambda line: None, progress_s=30.0)
    worker.queue.enqueue(Job(id="scan-fast", scan="scan", budget_s=120.0))
    child = SimpleNamespace(claim=worker.queue.claim(), log=tmp_path / "job.log")
    child.log.write_text(MID)
    reads = count_reads(monkeypatch)

    first = worker._progress_lines([child])
    assert len(first) == 1 and "4/7 s, step 38" in first[0], first
    assert worker._progress_lines([child]) == [] and worker._progress_lines([child]) == []
    assert reads == [child.log], "an unchanged log is not read again"
    with open(child.log, "a") as log:
        log.write(FULL)
    after = worker._progress_lines([child])
    assert len(after) == 1 and AFTER_TRAINING in after[0], after
    assert reads == [child.log] * 2
    worker._progress_lines([])
    assert worker._progress_lines([child]) and len(reads) == 3, "a job gone and back is read afresh"


def test_a_kept_reading_gives_the_note_a_fresh_reading_gives(tmp_path):
    queue = Queue.for_root(tmp_path)
    queue.enqueue(Job(id="scan-fast", scan="scan", budget_s=120.0))
    claim = queue.claim()
    log = tmp_path / "job.log"
    tails = LogTails()
    for text in ("", MID, MID + FULL):
        if text:
            log.write_text(text)
        for now in (claim.started + 10.0, claim.started + 50.0):  # the budget's share moves on: measured afresh
            assert (progress_note(claim, log, tmp_path, now=now, tails=tails)
                    == progress_note(claim, log, tmp_path, now=now)), (text, now)

