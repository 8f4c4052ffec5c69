"""The demo shows a live reconstruction as it runs (read from the scan's recon/live/status.json): a line each time
its state changes, its summary on the bar in front; it waits for the final result and says why when the live job
ends without one. The whole demo, live by default, runs in test_demo.py."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest

from spadscan import demo
from spadscan.demo import DemoError, DemoOptions, LiveWatch
from spadscan.protocol.live_status import LiveStatus, write_status


class Bar:
    def __init__(self):
        self.postfix = None

    def set_postfix_str(self, text: str) -> None:
        self.postfix = text


def live_folder(capture):
    folder = capture / "recon" / "live"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def test_the_live_state_is_said_when_it_changes_and_shown_on_the_bar(tmp_path):
    capture = tmp_path / "caps" / "demo-1"
    said = []
    watch = LiveWatch(capture, said.append)
    watch.bar = Bar()
    assert watch() is None and said == [] and watch.bar.postfix is None, "no status yet: nothing to show"
    write_status(live_folder(capture), LiveStatus(views_used=16, views_published=20, steps=300, chamfer_mm=4.25,
                                                  views_planned=128, job="demo-1-fast"))
    assert watch().steps == 300
    write_status(live_folder(capture), LiveStatus(views_used=20, views_published=24, steps=420, job="demo-1-fast"))
    watch()
    assert len(said) == 1 and said[0].startswith("live reconstruction following the scan: 16/20 views of 128")
    assert watch.bar.postfix == "live: 20/24 views, 420 steps"
    write_status(live_folder(capture), LiveStatus(views_used=24, views_published=24, steps=500, state="final",
                                                  chamfer_mm=2.5, job="demo-1-fast"))
    watch()
    assert len(said) == 2 and said[1].startswith("live reconstruction finishing: 24/24 views")
    assert watch.bar.postfix == "live: 24/24 views, 500 steps, Chamfer 2.50 mm"


@pytest.mark.parametrize("state", ["stopped", "aborted"])
def test_a_live_job_that_ends_without_a_result_fails_the_demo_saying_why(tmp_path, state):
    capture = tmp_path / "caps" / "demo-1"
    write_status(live_folder(capture), LiveStatus(views_used=0, views_published=3, steps=0, state=state,
                                                  note="capture demo-1: no measurements"))
    worker = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        with pytest.raises(DemoError) as info:
            demo._finish_live(DemoOptions(out=tmp_path, budget_s=5), tmp_path / "caps", "demo-1", worker,
                              tmp_path / "logs", LiveWatch(capture, lambda line: None))
    finally:
        worker.kill()
        worker.wait()
    assert str(info.value).startswith(f"the live reconstruction {state}: capture demo-1: no measurements (log: ")


def test_a_worker_that_exits_during_the_live_job_fails_the_demo(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "worker.log").write_text("spadscan: error: captures: not a folder\n")
    worker = subprocess.Popen([sys.executable, "-c", "raise SystemExit(2)"])
    worker.wait()
    with pytest.raises(DemoError) as info:
        demo._finish_live(DemoOptions(out=tmp_path, budget_s=5), tmp_path / "caps", "x", worker, logs,
                          LiveWatch(tmp_path / "caps" / "x", lambda line: None))
    assert str(info.value) == f"the worker exited with code 2: captures: not a folder (log: {logs / 'worker.log'})"


def test_a_scan_whose_job_ran_as_an_ordinary_one_ends_the_wait_when_the_queue_says_done(tmp_path):
    # A scan quicker than the worker's poll is queued complete, as an ordinary job: no live status ever appears.
    from spadscan.worker.jobs import Job
    from spadscan.worker.queue import Queue

    captures = tmp_path / "caps"
    queue = Queue.for_root(captures)
    queue.enqueue(Job(id="demo-1-fast", scan="demo-1"))
    worker = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    finished = threading.Event()

    def finish():
        try:
            demo._finish_live(DemoOptions(out=tmp_path, budget_s=5), captures, "demo-1", worker, tmp_path / "logs",
                              LiveWatch(captures / "demo-1", lambda line: None))
        finally:
            finished.set()

    waiter = threading.Thread(target=finish, daemon=True)
    try:
        waiter.start()
        assert not finished.wait(1.5), "the demo stopped waiting while the job was only queued"
        (queue.path / "queued" / "demo-1-fast.json").rename(queue.path / "done" / "demo-1-fast.json")
        assert finished.wait(60), "the demo went on waiting for a job the queue says is done"
    finally:
        worker.kill()
        worker.wait()
        waiter.join(60)
