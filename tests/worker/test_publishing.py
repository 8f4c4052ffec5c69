"""A worker killed (SIGKILL, a real process) at every step of publishing a result: every job ends with exactly one
result, the finished reconstruction is never run again once it is complete, and `--status` never says done without
its result. Also the states earlier versions left behind (a done job whose complete result is still in its scratch
folder; a done job with no result) are reconciled when a worker starts.

The jobs run `marker_recon` (test_worker_process): a marker per start and per end, a report.json as the result.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest

from spadscan.cli import main as cli_main
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import COMPLETE, Job, scratch_path
from spadscan.worker.kill_points import ENV, PUBLISH_STEPS, RECOVERY_STEPS
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from process_helpers import reaped
from test_watcher import make_scan
from test_worker_process import RECON, markers_of, start_worker

JOB = "s-fast"
pytestmark = pytest.mark.usefixtures("recon_stand_ins")  # the job processes import marker_recon


@pytest.fixture
def root(tmp_path):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    return root


@pytest.fixture
def markers(tmp_path, monkeypatch):
    d = tmp_path / "markers"
    d.mkdir()
    monkeypatch.setenv("MARKERS", str(d))  # for the job processes of the workers run in this process
    monkeypatch.delenv(ENV, raising=False)  # never kill the test itself
    return d


def killed_at(root: Path, markers: Path, step: str) -> None:
    """Run a worker process over `root` that kills itself at `step`; check that it did."""
    with reaped(start_worker(root, markers, once=True, sleep_s=0, env={ENV: step})) as (worker,):
        out = worker.communicate(timeout=120)[0]
    assert worker.returncode == -signal.SIGKILL, f"the worker was not killed at {step}: {out}"


def status_rows(root: Path, capsys) -> dict[str, dict]:
    """`spadscan worker --status` (table and JSON): a done job always names its result, and it is there."""
    assert cli_main(["worker", "--root", str(root), "--status"]) == 0
    table = capsys.readouterr().out
    assert "result: unknown" not in table, table
    assert cli_main(["worker", "--root", str(root), "--status", "--json"]) == 0
    rows = {r["id"]: r for r in json.loads(capsys.readouterr().out)}
    for row in rows.values():
        if row["state"] == "done":
            assert row["result"] and (Path(row["result"]) / "report.json").is_file(), row
    return rows


def run_to_the_end(root: Path, arun) -> tuple[dict, list[str]]:
    lines: list[str] = []
    config = WorkerConfig(root=root, once=True, poll_s=0.1, recon=RECON)
    return arun(Worker(config, log=lines.append).run(), timeout_s=120), lines


def exactly_one_result(root: Path, markers: Path, capsys, runs: int) -> None:
    """The job is done with its one result in place (report, job.log, completion marker), nothing left beside it,
    `--status` names it, and the reconstruction ran `runs` times to its end."""
    final = root / "s" / "recon" / JOB
    assert sorted(p.name for p in final.parent.iterdir()) == [JOB], "a scratch folder or a moved-aside result is left"
    assert {"report.json", "job.log", COMPLETE} <= {p.name for p in final.iterdir()}
    assert Queue.for_root(root).counts() == {"queued": 0, "running": 0, "done": 1, "failed": 0}
    row = status_rows(root, capsys)[JOB]
    assert (row["result"], row["kept"]) == (str(final), False)
    assert len(markers_of(markers, "s", "end")) == runs


@pytest.mark.slow
@pytest.mark.parametrize("step", PUBLISH_STEPS)
def test_a_worker_killed_at_any_step_of_publishing_loses_nothing(root, markers, arun, capsys, step):
    killed_at(root, markers, step)
    status_rows(root, capsys)
    run_to_the_end(root, arun)
    complete = PUBLISH_STEPS.index(step) >= PUBLISH_STEPS.index("marked-complete")
    exactly_one_result(root, markers, capsys, runs=1 if complete else 2)


@pytest.mark.slow
@pytest.mark.parametrize("left", ["marked-complete", "published"])
@pytest.mark.parametrize("step", [*RECOVERY_STEPS, "settled"])
def test_a_worker_killed_while_publishing_what_a_dead_worker_left_loses_nothing(root, markers, arun, capsys, left,
                                                                                step):
    killed_at(root, markers, left)
    with reaped(start_worker(root, markers, once=True, sleep_s=0, env={ENV: step})) as (recovering,):
        out = recovering.communicate(timeout=120)[0]
    if left == "published" and step == "recovered-published":
        assert recovering.returncode == 0, out  # nothing to move: the result is already in place
    else:
        assert recovering.returncode == -signal.SIGKILL, out
    status_rows(root, capsys)
    run_to_the_end(root, arun)
    exactly_one_result(root, markers, capsys, runs=1)


@pytest.mark.parametrize("meanwhile", ["queued again", "failed"])
@pytest.mark.parametrize("left", ["marked-complete", "published"])
def test_a_finished_result_is_kept_when_another_worker_took_the_job_over_first(root, markers, arun, capsys, left,
                                                                            meanwhile):
    """The dead worker's claim was taken over (queued again, or failed: no attempts left) before a worker looked
    at its result: the result is still published, once, and the job is done."""
    killed_at(root, markers, left)
    queue = Queue(root / ".queue", max_attempts=1 if meanwhile == "failed" else 3)
    assert queue.reclaim_expired() == [(JOB, "failed" if meanwhile == "failed" else "queued")]
    settled, lines = run_to_the_end(root, arun)
    exactly_one_result(root, markers, capsys, runs=1)
    assert not any("not run" in line for line in lines), "the job's own result is not 'kept' from elsewhere"


def test_a_done_jobs_result_left_in_its_scratch_folder_is_published_not_deleted(root, markers, arun, capsys):
    """What an earlier version left when killed as its job reached done/: the job done, its complete result still in
    the scratch folder (no job.log, no marker), no result folder, no result in the record."""
    queue = Queue.for_root(root)
    queue.enqueue(Job(id=JOB, scan="s"))
    claim = queue.claim(Holder(**{**Holder.current().to_dict(), "pid": _gone_pid(), "pid_start": ""}))
    scratch = scratch_path(claim.job, root, claim.token)
    scratch.mkdir(parents=True)
    (scratch / "report.json").write_text('{"steps": 7}')
    (scratch / "mesh.ply").write_text("a mesh")
    assert queue.finish(claim)  # done, its record naming no result
    settled, lines = run_to_the_end(root, arun)
    final = root / "s" / "recon" / JOB
    assert json.loads((final / "report.json").read_text()) == {"steps": 7} and not scratch.exists()
    assert any("published the finished result" in line and str(final) in line for line in lines), lines
    assert not any("removed the partial result" in line for line in lines)
    assert status_rows(root, capsys)[JOB]["result"] == str(final)
    assert not markers_of(markers, "s", "start"), "the finished job is not run again"


def test_a_done_job_whose_result_is_gone_runs_again(root, markers, arun, capsys):
    settled, _ = run_to_the_end(root, arun)
    assert settled == {JOB: "done"}
    final = root / "s" / "recon" / JOB
    for p in final.iterdir():
        p.unlink()
    final.rmdir()
    settled, lines = run_to_the_end(root, arun)
    assert settled == {JOB: "done"}
    assert any(f"{JOB}: done, but its result {final} is missing: queued again" in line for line in lines), lines
    exactly_one_result(root, markers, capsys, runs=2)


def test_a_done_job_whose_scan_was_moved_away_stays_done(root, markers, arun, capsys):
    """A lab archives a finished scan (moves its folder out of the root): its job is not run again, nor failed."""
    import shutil

    settled, _ = run_to_the_end(root, arun)
    assert settled == {JOB: "done"}
    shutil.move(root / "s", root.parent / "archive-s")
    settled, lines = run_to_the_end(root, arun)
    assert settled == {}, lines
    capsys.readouterr()
    assert cli_main(["worker", "--root", str(root), "--status"]) == 0
    (row,) = [line for line in capsys.readouterr().out.splitlines() if line.startswith(JOB)]
    assert " done " in row and row.endswith("(no longer there)"), row
    assert len(markers_of(markers, "s", "start")) == 1


def _gone_pid() -> int:
    import subprocess
    import sys

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    return gone.pid


def test_the_completion_marker_is_written_after_every_file_of_the_result_is_on_disk(tmp_path, monkeypatch):
    """After a power cut the marker must not outlive a mesh still in the page cache: each file and folder is synced
    before the marker is written."""
    import os

    from spadscan.worker.jobs import mark_complete

    folder = tmp_path / ".tmp-s-fast-abc"
    (folder / "pictures").mkdir(parents=True)
    for name in ("mesh.ply", "report.json", "pictures/mesh.png"):
        (folder / name).write_text(name)
    order: list[str] = []
    fsync = os.fsync

    def noted(fd):
        order.append(os.path.relpath(os.readlink(f"/proc/self/fd/{fd}"), folder))
        return fsync(fd)

    monkeypatch.setattr(os, "fsync", noted)
    mark_complete(folder, "s-fast", "abc", tmp_path / ".queue")
    marker = order.index(f"{COMPLETE}.tmp")
    assert {"mesh.ply", "report.json", "pictures", os.path.join("pictures", "mesh.png")} <= set(order[:marker])
    assert order[marker + 1:] == ["."], "then the folder, with the marker renamed into place"
