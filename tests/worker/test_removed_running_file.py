"""A running job's file removed from running/ by hand (no other worker took the job over): the job is not lost. Its
worker puts it in failed/ from its registered file (ids/), saying why, stops its process or drops its finished
result, and `--retry-failed` queues it again."""

from __future__ import annotations

import pytest

from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue

from process_helpers import reaped
from test_watcher import make_scan
from test_worker_process import markers_of, pid_alive, start_worker, wait_for


@pytest.fixture
def markers(tmp_path):
    d = tmp_path / "markers"
    d.mkdir()
    return d


@pytest.mark.parametrize("when", ["while it runs", "once it has finished"])
def test_a_running_jobs_file_removed_by_hand_puts_the_job_in_failed(tmp_path, markers, when):
    root, release = tmp_path / "captures", tmp_path / "release"
    root.mkdir()
    make_scan(root, "a")
    # A short lease is renewed (and its loss seen) every half second; a long one not before the job has finished.
    lease_s = 2.0 if when == "while it runs" else 60.0
    with reaped(start_worker(root, markers, once=True, sleep_s=0.0, lease_s=lease_s,
                             env={"RELEASE": str(release)})) as (worker,):
        wait_for(lambda: markers_of(markers, "a", "start"))
        queue = Queue.for_root(root)
        (claimed,) = (queue.path / "running").glob("a-fast~*.json")
        claimed.unlink()
        if when == "once it has finished":
            release.touch()
            wait_for(lambda: markers_of(markers, "a", "end"))
        log = worker.communicate(timeout=60)[0]
    assert worker.returncode == 0, log  # it went on, and ended once nothing was queued or running
    assert queue.counts() == {"queued": 0, "running": 0, "done": 0, "failed": 1}, log
    (record,) = queue.records("a-fast")
    assert record["outcome"] == "failed" and "was removed while it ran" in record["error"], record
    said = next(line for line in log.splitlines() if "was removed while it ran" in line)
    assert "the job is in failed/" in said and "--retry-failed" in said, log
    if when == "while it runs":
        assert "stopping its process" in said
        assert not markers_of(markers, "a", "end"), "its process was stopped"
        assert not any(pid_alive(pid) for pid in markers_of(markers, "a", "start"))
    else:
        assert "result dropped" in said
    assert not (root / "a" / "recon" / "a-fast").exists()
    assert queue.retry_failed("a-fast") == ["a-fast"] and queue.counts()["queued"] == 1


def test_a_job_taken_over_or_settled_elsewhere_is_not_put_back(tmp_path):
    q = Queue(tmp_path / "q", lease_s=10, max_attempts=3)
    q.enqueue(Job(id="s-fast", scan="s", preset="fast"))
    claim = q.claim()
    taken = claim.path.with_name("s-fast~another.json")
    claim.path.rename(taken)  # another worker's take-over renames the file to a token of its own
    assert not q.restore_removed(claim, "gone") and q.counts()["failed"] == 0
    taken.rename(q.path / "done" / "s-fast.json")  # and settled it
    assert not q.restore_removed(claim, "gone") and q.counts() == {"queued": 0, "running": 0, "done": 1, "failed": 0}
    (q.path / "done" / "s-fast.json").unlink()  # gone from every state folder: put back in failed/
    assert q.restore_removed(claim, "gone") and q.counts()["failed"] == 1
    assert q.job_in("failed", "s-fast") == claim.job
