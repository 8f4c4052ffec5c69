"""A finished result is never replaced in silence: a job whose results folder already holds one is not run again (a
fresh queue, a deleted queue), and a result that appears while a job runs is moved aside, not deleted."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from spadscan.cli import main as cli_main
from spadscan.worker.jobs import publish
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.watcher import JobOptions
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan

HERE = Path(__file__).resolve().parent
RECON = "test_worker_process:options_recon"  # writes {"device", "seed", "steps"} into report.json


def run_once(root: Path, arun, steps: int, queue_dir: Path | None = None) -> tuple[dict, list[str]]:
    lines: list[str] = []
    config = WorkerConfig(root=root, once=True, poll_s=0.1, recon=RECON, queue_dir=queue_dir,
                          options=JobOptions(steps=steps))
    return arun(Worker(config, log=lines.append).run(), timeout_s=120), lines


def report_of(root: Path, scan: str) -> dict:
    return json.loads((root / scan / "recon" / f"{scan}-fast" / "report.json").read_text())


def test_a_fresh_queue_keeps_the_results_already_there(tmp_path, arun, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]))
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
    rows = {r.id: r for r in Queue(tmp_path / "q2").statuses()}
    assert (rows["s-fast"].state, rows["s-fast"].result, rows["s-fast"].kept) == ("done", str(result), True)
    assert rows["new-fast"].kept is False
    assert [p.name for p in (root / "s" / "recon").iterdir()] == ["s-fast"], "nothing moved aside or left over"


def test_a_deleted_queue_does_not_rerun_finished_jobs(tmp_path, arun, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]))
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
    assert json.loads((result / "report.json").read_text()) == {"steps": 20}
    assert cli_main(["worker", "--root", str(tmp_path), "--status"]) == 0
    assert "kept, not run" in capsys.readouterr().out


def test_an_empty_results_folder_is_not_a_result(tmp_path, arun, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]))
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
