"""`spadscan worker` refuses what it would otherwise ignore: a capture given as the captures root, flags that do not go
together; and it says when the options given do not apply (jobs queued earlier keep their own)."""

from __future__ import annotations

from pathlib import Path

import pytest

from spadscan.cli import main as cli_main
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.watcher import JobOptions, scan_once
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan


def one_line_error(capsys) -> str:
    captured = capsys.readouterr()
    assert captured.out == "" and len(captured.err.strip().splitlines()) == 1, captured
    return captured.err.strip()


@pytest.mark.parametrize("flags", [["--once"], ["--status"], ["--retry-failed"]])
def test_a_capture_given_as_the_root_is_refused(tmp_path, capsys, flags):
    make_scan(tmp_path, "sph")
    capture = tmp_path / "sph"
    assert cli_main(["worker", "--root", str(capture), *flags]) == 1
    assert one_line_error(capsys) == (f"spadscan: error: {capture} holds scan.json: it is a capture, not a captures "
                                      f"root (use --root {tmp_path})")
    assert not (capture / ".queue").exists(), "nothing left inside the capture"


def test_a_capture_given_as_the_root_is_refused_by_the_config_too(tmp_path):
    from spadscan.protocol.errors import ConfigError

    make_scan(tmp_path, "sph")
    with pytest.raises(ConfigError, match="it is a capture, not a captures root"):
        WorkerConfig(root=tmp_path / "sph").check()


@pytest.mark.parametrize("flags, message", [
    (["--json"], "--json goes only with --status (it prints the job list as JSON)"),
    (["--json", "--once"], "--json goes only with --status (it prints the job list as JSON)"),
    (["--status", "--once"], "--status only lists the jobs: --once does not go with it"),
    (["--status", "--retry-failed"], "--status only lists the jobs: --retry-failed does not go with it"),
    (["--status", "--steps", "3", "--processes", "2"],
     "--status only lists the jobs: --processes, --steps do not go with it"),
    (["--retry-failed", "--once"], "--retry-failed only queues failed jobs again and exits (run the worker after "
                                   "it): --once does not go with it"),
    (["--redo", "s-fast", "--once", "--preset", "paper"], "--redo only queues the done jobs it names again and exits "
                                                          "(their ids name their preset): --once, --preset do not go "
                                                          "with it"),
    (["--status", "--redo", "s-fast"], "--status only lists the jobs: --redo does not go with it"),
])
def test_flags_that_would_be_ignored_are_refused(tmp_path, capsys, flags, message):
    make_scan(tmp_path, "s")
    assert cli_main(["worker", "--root", str(tmp_path), *flags]) == 1
    assert one_line_error(capsys) == f"spadscan: error: {message}"
    assert not (tmp_path / ".queue").exists()


def test_status_and_retry_on_a_fresh_root_create_nothing(tmp_path, capsys):
    make_scan(tmp_path, "s")
    assert cli_main(["worker", "--root", str(tmp_path), "--status", "--json"]) == 0
    assert capsys.readouterr().out.strip() == "[]"
    assert cli_main(["worker", "--root", str(tmp_path), "--status", "--lease-s", "5"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == f"no jobs in {tmp_path / '.queue'}"
    assert cli_main(["worker", "--root", str(tmp_path), "--retry-failed", "--device", "cpu"]) == 0
    assert capsys.readouterr().out.strip() == "no failed jobs"
    assert not (tmp_path / ".queue").exists()


def run_once(root: Path, arun, **config) -> list[str]:
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.1, recon="test_worker_process:options_recon",
                                 **config), log=lines.append)
    arun(worker.run(), timeout_s=120)
    return lines


@pytest.mark.usefixtures("recon_stand_ins")
def test_queued_jobs_whose_frozen_options_differ_are_named(tmp_path, arun):
    for name in ("a", "b", "c"):
        make_scan(tmp_path, name)
    scan_once(tmp_path, Queue.for_root(tmp_path), JobOptions(steps=20, seed=4))  # queued by an earlier worker
    lines = run_once(tmp_path, arun, options=JobOptions(steps=10, seed=4), options_given=("steps", "seed"))
    note = [line for line in lines if "queued earlier" in line]
    assert note == ["3 job(s) queued earlier keep the options they were queued with, not steps 10, seed 4: "
                    "a-fast (steps 20), b-fast (steps 20), c-fast (steps 20)"], lines


@pytest.mark.usefixtures("recon_stand_ins")
def test_no_note_when_the_options_given_match_or_none_are_given(tmp_path, arun):
    make_scan(tmp_path, "a")
    scan_once(tmp_path, Queue.for_root(tmp_path), JobOptions(steps=20))
    lines = run_once(tmp_path, arun, options=JobOptions(seed=0), options_given=("seed",))
    assert not [line for line in lines if "queued earlier" in line], lines


def test_the_command_passes_the_options_given(tmp_path, monkeypatch):
    """Only the flags given are compared with the queued jobs' own options."""
    import spadscan.worker.pool as pool

    seen = {}

    async def fake_run_worker(config):
        seen["config"] = config
        return pool.WorkerRun(settled={}, left={})

    monkeypatch.setattr(pool, "run_worker", fake_run_worker)
    assert cli_main(["worker", "--root", str(tmp_path), "--once", "--steps", "10"]) == 0
    assert seen["config"].options_given == ("steps",) and seen["config"].options.steps == 10
    assert (seen["config"].processes, seen["config"].poll_s, seen["config"].lease_s) == (1, 2.0, 60.0)
