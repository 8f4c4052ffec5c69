"""A finished result is never replaced in silence: a job whose results folder already holds one is not run again (a
fresh queue, a deleted queue), and a result that appears while a job runs is moved aside, not deleted."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from spadscan.cli import main as cli_main
from spadscan.worker.jobs import publish
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.watcher import JobOptions
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan

RECON = "test_worker_process:options_recon"  # writes {"device", "seed", "steps"} into report.json


def run_once(root: Path, arun, steps: int, queue_dir: Path | None = None) -> tuple[dict, list[str]]:
    lines: list[str] = []
    config = WorkerConfig(root=root, once=True, poll_s=0.1, recon=RECON, queue_dir=queue_dir,
                          options=JobOptions(steps=steps))
    return arun(Worker(config, log=lines.append).run(), timeout_s=120), lines


def report_of(root: Path, scan: str) -> dict:
    return json.loads((root / scan / "recon" / f"{scan}-fast" / "report.json").read_text())


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_fresh_queue_keeps_the_results_already_there(tmp_path, arun):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    assert run_once(root, arun, steps=20)[0] == {"s-fast": "done"}
    make_scan(root, "new")  # a scan with no result yet still runs

    settled, lines = run_once(root, arun, steps=3, queue_dir=tmp_path / "q2")
    assert settled == {"s-fast": "kept", "new-fast": "done"}
    assert report_of(root, "s")["steps"] == 20, "the 20-step result is still there"
    assert report_of(root, "new")["steps"] == 3
    result = root / "s" / "recon" / "s-fast"
    assert any(f"s-fast: not run, {result} already holds a result" in line for line in lines), lines
    redo = f"`spadscan worker --root {root} --queue {tmp_path / 'q2'} --redo s-fast`"
    assert any(redo in line for line in lines), "the command it suggests names this worker's queue"
    assert any(f"{redo} moves this one aside and queues the job again; a worker on this queue then reconstructs it"
               in line for line in lines), "the command only queues the job: a worker runs it"
    rows = {r.id: r for r in Queue(tmp_path / "q2").statuses()}
    assert (rows["s-fast"].state, rows["s-fast"].result, rows["s-fast"].kept) == ("done", str(result), True)
    assert rows["new-fast"].kept is False
    assert [p.name for p in (root / "s" / "recon").iterdir()] == ["s-fast"], "nothing moved aside or left over"


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_deleted_queue_does_not_rerun_finished_jobs(tmp_path, arun):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    assert run_once(root, arun, steps=20)[0] == {"s-fast": "done"}
    shutil.rmtree(root / ".queue")
    assert run_once(root, arun, steps=3)[0] == {"s-fast": "kept"}
    assert report_of(root, "s")["steps"] == 20


def test_the_command_says_how_many_jobs_it_did_not_run(tmp_path, capsys):
    """No reconstruction starts at all: the result is there, so the torch reconstruction is never loaded."""
    make_scan(tmp_path, "s")
    result = tmp_path / "s" / "recon" / "s-fast"
    result.mkdir(parents=True)
    (result / "report.json").write_text('{"steps": 20}')
    assert cli_main(["worker", "--root", str(tmp_path), "--once", "--steps", "3"]) == 0
    captured = capsys.readouterr()
    assert "0 done, 0 failed, 1 not run (their results were already there)" in captured.out
    assert f"s-fast: not run, {result} already holds a result" in captured.err
    assert f"`spadscan worker --root {tmp_path} --redo s-fast`" in captured.err  # the default queue: no --queue
    assert json.loads((result / "report.json").read_text()) == {"steps": 20}
    assert cli_main(["worker", "--root", str(tmp_path), "--status"]) == 0
    assert "kept, not run" in capsys.readouterr().out


@pytest.mark.usefixtures("recon_stand_ins")
def test_an_empty_results_folder_is_not_a_result(tmp_path, arun):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    (root / "s" / "recon" / "s-fast").mkdir(parents=True)
    settled, lines = run_once(root, arun, steps=3)
    assert settled == {"s-fast": "done"} and report_of(root, "s")["steps"] == 3
    aside = [p for p in (root / "s" / "recon").iterdir() if ".replaced-" in p.name]
    assert len(aside) == 1 and not any(aside[0].iterdir()), "even an empty folder is moved aside, not deleted"
    assert any(f"moved it to {aside[0]}" in line for line in lines), lines


def test_publishing_moves_an_earlier_result_aside(tmp_path):
    final, scratch = tmp_path / "recon" / "s-fast", tmp_path / "recon" / ".tmp-s-fast-x"
    for folder, text in ((final, "old"), (scratch, "new")):
        folder.mkdir(parents=True)
        (folder / "mesh.ply").write_text(text)
    published, aside = publish(scratch, final)
    assert published == final and (final / "mesh.ply").read_text() == "new"
    assert aside.parent == final.parent and aside.name.startswith("s-fast.replaced-")
    assert (aside / "mesh.ply").read_text() == "old"
    (tmp_path / "other").mkdir()
    assert publish(tmp_path / "other", tmp_path / "recon" / "t-fast") == (tmp_path / "recon" / "t-fast", None)


@pytest.mark.usefixtures("recon_stand_ins")
def test_redo_moves_the_result_aside_and_runs_the_job_again(tmp_path, arun, capsys):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    make_scan(root, "t")
    assert run_once(root, arun, steps=20)[0] == {"s-fast": "done", "t-fast": "done"}
    assert cli_main(["worker", "--root", str(root), "--redo", "s-fast", "--steps", "3"]) == 0
    out = capsys.readouterr().out.strip()
    (aside,) = [p for p in (root / "s" / "recon").iterdir() if p.name.startswith("s-fast.replaced-")]
    assert out == f"queued again: s-fast (with --steps 3); its earlier result is now {aside}"
    assert json.loads((aside / "report.json").read_text())["steps"] == 20
    assert run_once(root, arun, steps=20)[0] == {"s-fast": "done"}, "only the job named runs again"
    assert report_of(root, "s")["steps"] == 3 and report_of(root, "t")["steps"] == 20
    (row,) = [r for r in Queue.for_root(root).statuses() if r.id == "s-fast"]
    assert (row.state, row.attempts, row.kept) == ("done", 1, False)


@pytest.mark.parametrize("job, message", [
    ("nope-fast", "no job nope-fast in {queue} (`--status` lists the jobs)"),
    ("q-fast", "q-fast is queued, not done: --redo queues finished jobs again"),
    ("f-fast", "f-fast is failed, not done: --redo queues finished jobs again (--retry-failed queues failed ones)"),
])
def test_redo_refuses_jobs_that_are_not_done_and_moves_nothing(tmp_path, capsys, job, message):
    from spadscan.worker.watcher import scan_once

    for name in ("done", "q", "f"):
        make_scan(tmp_path, name)
    queue = Queue.for_root(tmp_path)
    scan_once(tmp_path, queue, JobOptions())
    while (claim := queue.claim()) is not None and claim.job.id != "q-fast":
        if claim.job.id == "f-fast":
            queue.fail(claim, "boom", retry=False)
        else:
            queue.finish(claim, "x")
    queue.release(claim)
    result = tmp_path / "done" / "recon" / "done-fast"
    result.mkdir(parents=True)
    (result / "report.json").write_text("{}")
    assert cli_main(["worker", "--root", str(tmp_path), "--redo", "done-fast", job]) == 1
    captured = capsys.readouterr()
    assert captured.err.strip() == "spadscan: error: " + message.format(queue=queue.path) and captured.out == ""
    assert (result / "report.json").exists(), "nothing moved when one of the jobs named cannot be redone"
    assert queue.counts() == {"queued": 1, "running": 0, "done": 1, "failed": 1}


def removing_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                   started=None):
    """A stand-in reconstruction whose scan is deleted while it runs: it fails on its input, as the real one does."""
    from spadscan.protocol.errors import CaptureError

    if steps == 1:  # the scan whose folder goes
        shutil.rmtree(capture)
    raise CaptureError(f"{capture}: missing")


@pytest.mark.usefixtures("recon_stand_ins")
@pytest.mark.parametrize("steps, gone", [(1, True), (2, False)])
def test_a_failed_job_whose_scan_is_gone_is_not_said_to_be_worth_a_retry(tmp_path, arun, steps, gone):
    make_scan(tmp_path, "s")
    lines: list[str] = []
    config = WorkerConfig(root=tmp_path, once=True, poll_s=0.1, recon="test_worker_results:removing_recon",
                          options=JobOptions(steps=steps))
    arun(Worker(config, log=lines.append).run(), timeout_s=120)
    (failed,) = [line for line in lines if line.startswith("s-fast failed after ")]
    assert failed.endswith(f"(its scan s is gone from {tmp_path}: nothing to try again)") == gone, failed
    assert ("--retry-failed" in failed) != gone, failed
