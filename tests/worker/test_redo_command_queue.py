"""The `redo` command a result's job.json records works as written: for a worker on a queue of its own (--queue), it
names that queue, absolute and quoted, so that run from anywhere it finds the job and queues it again there."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest

from spadscan.cli import main as cli_main
from spadscan.worker.jobs import Job, execute_job, redo_command
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.watcher import JobOptions
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan
from test_worker_process import options_recon

RECON = "test_worker_process:options_recon"


def run_once(root: Path, queue_dir: Path, arun) -> dict:
    config = WorkerConfig(root=root, once=True, poll_s=0.1, recon=RECON, queue_dir=queue_dir,
                          options=JobOptions(steps=3))
    return arun(Worker(config, log=lambda line: None).run(), timeout_s=120)


def recorded_redo(root: Path) -> str:
    return json.loads((root / "s" / "recon" / "s-fast" / "job.json").read_text())["redo"]


def run_as_written(command: str) -> int:
    words = shlex.split(command)
    assert words[:2] == ["spadscan", "worker"], command
    return cli_main(words[1:])


@pytest.mark.usefixtures("recon_stand_ins")
def test_the_recorded_redo_finds_the_job_in_the_workers_own_queue(tmp_path, arun, monkeypatch, capsys):
    root, elsewhere = tmp_path / "captures", tmp_path / "elsewhere"
    root.mkdir()
    elsewhere.mkdir()
    make_scan(root, "s")
    monkeypatch.chdir(tmp_path)
    queue_dir = Path("my queue")  # relative, as typed after --queue, and a name the shell would split
    assert run_once(root, queue_dir, arun) == {"s-fast": "done"}
    redo = recorded_redo(root)
    monkeypatch.chdir(elsewhere)  # a report is read, and its command run, from anywhere
    assert run_as_written(redo) == 0, capsys.readouterr().err
    assert capsys.readouterr().out.startswith("queued again: s-fast"), redo
    assert Queue(tmp_path / "my queue", create=False).counts()["queued"] == 1
    assert not (root / ".queue").exists(), "the root's default queue is not the one the job is in"


def test_the_redo_command_names_a_queue_only_when_it_is_not_the_roots_own(tmp_path, monkeypatch):
    job = Job(id="s-fast", scan="s")
    monkeypatch.chdir(tmp_path)
    root = tmp_path / "captures"
    assert redo_command(job, Path("captures")) == f"spadscan worker --root {root} --redo s-fast"
    assert redo_command(job, root, Path("captures/.queue")) == f"spadscan worker --root {root} --redo s-fast"
    assert (redo_command(job, root, Path("q 2")) ==
            f"spadscan worker --root {root} --queue '{tmp_path / 'q 2'}' --redo s-fast")


def test_a_live_jobs_final_run_records_the_queue_too(tmp_path):
    root, queue_dir = tmp_path / "captures", tmp_path / "q2"
    make_scan(root, "s")  # complete when its live job starts: the job reconstructs it as an ordinary one
    out = tmp_path / "out"
    execute_job(Job(id="s-fast", scan="s", live=True), root, out, options_recon, queue=queue_dir)
    redo = json.loads((out / "job.json").read_text())["redo"]
    assert redo == f"spadscan worker --root {root} --queue {queue_dir} --redo s-fast"


def test_help_says_redo_and_retry_failed_queue_jobs_for_a_worker_to_run(capsys):
    with pytest.raises(SystemExit):
        cli_main(["worker", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--redo JOB [JOB ...] queue these done jobs again, and exit (a worker on the root and queue then " \
           "reconstructs them)" in text, text
    assert "--redo mug-fast --steps 400 # queue a finished scan again (a worker reruns it)" in text
    assert "--retry-failed --device cpu # ... to run on the CPU" in text
    assert "queues the job again and exits: a worker on that root and queue" in text
