"""A live job whose scan the operator aborted ends as what it is: while its process ends, the worker's terminal says
its live reconstruction ended with the scan (not that it is setting up), and its end line and attempt record say the
scan was aborted by the operator, with nothing to retry (no `--retry-failed` advice)."""

from __future__ import annotations

import datetime as _dt
import json
from types import SimpleNamespace

import pytest

from spadscan.protocol.live_status import LiveStatus, read_status, status_path, write_status
from spadscan.worker.jobs import Job
from spadscan.worker.job_progress import SETTING_UP, progress_note
from spadscan.worker.live.job import ScanAborted
from spadscan.worker.pool import Worker
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from live_helpers import ReplayScan
from test_live_job import LiveJobThread, small_settings

ABORTED = "scan aborted by the operator: nothing to retry"


def settle(worker: Worker, claim, outcome: dict, returncode: int, tmp_path) -> None:
    """The worker settles the job process of `claim` that ended with `outcome` and `returncode`."""
    (outcome_file := tmp_path / "outcome.json").write_text(json.dumps(outcome))
    worker._settle(SimpleNamespace(claim=claim, proc=SimpleNamespace(returncode=returncode),
                                   scratch=tmp_path / "scratch", outcome=outcome_file, log=tmp_path / "job.log",
                                   stopped_why=None))


def test_a_live_job_whose_scan_is_aborted_ends_saying_so_with_nothing_to_retry(cylinder_capture, tmp_path,
                                                                                one_thread):
    root = tmp_path / "captures"
    scan = ReplayScan(cylinder_capture, root / "cyl")
    scan.publish(8)
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root), log=lines.append)
    worker.queue.enqueue(Job(id="cyl-fast", scan="cyl", live=True, device="cpu"))
    claim = worker.queue.claim()
    log = tmp_path / "job.log"  # a live job's log shows no progress bar while it follows its scan
    live = LiveJobThread(root, "cyl", small_settings())
    live.wait_status(lambda s: s.state == "live" and s.steps > 0, "a fit")
    assert progress_note(claim, log, root).stage == "live: live"

    scan.finish("aborted", "aborted by user")  # as `spadscan ctl abort` ends it
    with pytest.raises(ScanAborted) as err:
        live.join()
    note = progress_note(claim, log, root)  # the job's process has ended; the worker has not reaped it yet
    assert note.stage == "live: aborted" and SETTING_UP not in note.text, note
    assert note.text.startswith("cyl-fast: live reconstruction ended (the scan was aborted): "), note
    assert "aborted by user" in note.text

    settle(worker, claim, {"ok": False, "kind": "input", "error": str(err.value)}, 1, tmp_path)
    said = lines[-1]
    assert said.startswith("cyl-fast ended after ") and ABORTED in said, said
    assert "--retry-failed" not in said and "failed" not in said, said
    (record,) = worker.queue.records("cyl-fast")
    assert record["error"].startswith(ABORTED) and "aborted by user" in record["error"], record
    assert not record["retried"] and worker.queue.job_paths()["cyl-fast"][0] == "failed"
    assert read_status(status_path(root / "cyl")).state == "aborted", "the live status keeps the job's own word"


@pytest.mark.parametrize("last_word", ["stopped", "aborted"])
def test_an_earlier_attempts_last_word_is_not_taken_for_this_ones_nor_another_failure_for_an_abort(tmp_path,
                                                                                                   last_word):
    root = tmp_path / "captures"
    (folder := root / "cyl" / "recon" / "live").mkdir(parents=True)
    queue = Queue.for_root(root)
    queue.enqueue(Job(id="cyl-fast", scan="cyl", live=True, device="cpu"))
    claim = queue.claim()  # the job run again (--retry-failed): its new process has not written its first status yet
    earlier = _dt.datetime.fromtimestamp(claim.started - 60.0, _dt.timezone.utc).isoformat(timespec="milliseconds")
    write_status(folder, LiveStatus(views_used=8, views_published=9, steps=40, state=last_word, job="cyl-fast",
                                    note="the earlier attempt's end", updated_utc=earlier))
    note = progress_note(claim, tmp_path / "job.log", root, now=claim.started + 5.0)
    assert note.stage == SETTING_UP, note

    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, max_attempts=1), log=lines.append)
    settle(worker, claim, {"ok": False, "kind": "input", "error": "capture cyl: chunk-000007 unreadable"}, 1, tmp_path)
    assert ABORTED not in lines[-1] and "--retry-failed" in lines[-1], lines


@pytest.mark.parametrize("live", [False, True])
def test_a_job_that_failed_on_an_aborted_scan_ends_with_nothing_to_retry(tmp_path, live):
    """An ordinary job, or the second live job of a scan run as an ordinary one once the scan ended
    (`Queue.live_claim`), fails on a scan the operator aborted without a live status of its own: its scan's
    manifest says aborted, so a retry would fail the same way."""
    root = tmp_path / "captures"
    (root / "cyl").mkdir(parents=True)
    (root / "cyl" / "scan.json").write_text(json.dumps({"state": "aborted", "reason": "aborted by user"}))
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root), log=lines.append)
    worker.queue.enqueue(Job(id="cyl-fast", scan="cyl", live=live, device="cpu"))
    claim = worker.queue.claim()
    error = f"{root / 'cyl'}: scan state is 'aborted', not 'complete'"
    settle(worker, claim, {"ok": False, "kind": "input", "error": error}, 1, tmp_path)
    assert ABORTED in lines[-1] and "--retry-failed" not in lines[-1], lines
    (record,) = worker.queue.records("cyl-fast")
    assert record["error"].startswith(ABORTED) and "not 'complete'" in record["error"], record
