"""The page says the daemon's state in the daemon's own words (`spadscan ctl status`: scanning, paused, idle), and
says in one line at the top what the reconstruction side is doing: a worker at a job, jobs that no worker takes, a
scan that no worker has queued, a worker waiting for scans, or no worker at all, with the command that starts a worker
where none runs and the worker's terminal where one runs and does not do its work."""

from __future__ import annotations

import os
import shlex
import time

from dashboard_helpers import complete_scan, serving, status
from page_helpers import add_pose, browser_page, start_scan
from spadscan.commands.dashboard import daemon_running
from spadscan.daemon.root_lock import RootLock
from spadscan.dashboard.server import address
from spadscan.dashboard.worker_state import LOOK_S
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job
from spadscan.worker.presence import Presence, remove_presence, write_presence
from spadscan.worker.queue import Queue

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine


def text_of(page, selector: str, part: str) -> str:
    """The text of `selector` once it holds `part`."""
    page.wait_for_function("([s, t]) => (document.querySelector(s) || {}).textContent?.includes(t)",
                           arg=[selector, part], timeout=WAIT_MS)
    return page.locator(selector).text_content()


def aged(path, seconds: float) -> None:
    """`path` last written `seconds` ago (a scan that ended, a job queued, that long ago)."""
    then = time.time() - seconds
    os.utime(path, (then, then))


def test_a_scan_being_recorded_reads_scanning_as_the_daemon_says_it(tmp_path):
    writer, poses = start_scan(tmp_path / "s1", 8)
    add_pose(writer, poses, 0)
    lock = RootLock(tmp_path)
    with lock, serving(tmp_path, daemon_running=daemon_running) as server, browser_page() as (page, seen):
        assert status(server)["current"]["state"] == "running"  # scan.json's word, kept in the answer
        page.goto(address(server))
        assert text_of(page, "#daemon", "daemon") == " · daemon: scanning s1"
        assert page.locator("#current-state").text_content() == "scanning"
        assert page.locator('#scans tr[data-scan="s1"] td').nth(1).text_content() == "scanning"
        for i in range(1, len(poses)):  # the rest of the plan: a complete scan holds every planned pose
            add_pose(writer, poses, i)
        writer.finish()
        assert text_of(page, "#daemon", "idle") == " · daemon: idle"
    assert not seen.errors, seen.errors


def test_the_page_tells_an_idle_worker_from_none_and_says_how_to_start_one(tmp_path):
    start = f"spadscan worker --root {shlex.quote(str(tmp_path.resolve()))}"
    me = Holder.current()
    worker = f"worker on {me.host} pid {me.pid}"
    queue = Queue.for_root(tmp_path)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        said = text_of(page, "#worker", "no worker is running")
        assert said == ("no worker is running (a worker queues and reconstructs each scan once it is complete): "
                        f"start one with `{start}`"), said
        started = Presence(me.to_dict(), str(tmp_path), time.time(), 1)
        write_presence(queue.path, started)  # a worker starts
        assert text_of(page, "#worker", "waiting") == f"{worker}: waiting for scans (it queues each once complete)"
        complete_scan(tmp_path / "mug", 2)  # a scan the worker does not queue
        aged(tmp_path / "mug" / "scan.json", 3 * LOOK_S)
        said = text_of(page, "#worker", "mug")
        assert said.startswith(f"the {worker} has not queued scan mug") and said.endswith("see its terminal"), said
        assert page.locator("#worker").get_attribute("class") == "down"
        remove_presence(queue.path, started)  # the worker stops
        said = text_of(page, "#worker", "no worker has")
        assert said.startswith("no worker has queued scan mug") and start in said, said
        queue.enqueue(Job(id="mug-fast", scan="mug"))  # queued by a worker that went, say
        aged(queue.path / "queued" / "mug-fast.json", 2 * LOOK_S)
        said = text_of(page, "#worker", "waited")
        assert said.startswith("1 job has waited") and "no worker has taken it" in said and start in said, said
        queue.claim(me)  # a worker takes it
        assert text_of(page, "#worker", "reconstructing") == "worker: reconstructing mug-fast"
        assert page.locator("#worker").get_attribute("class") == ""
    assert not seen.errors, seen.errors


def test_what_the_worker_line_is_made_of():
    from spadscan.dashboard.scans import ScanRow
    from spadscan.dashboard.worker_state import worker_state

    now = 1_000_000.0
    running = {"id": "a-fast", "scan": "a", "state": "running", "stale": None}
    queued = {"id": "b-fast", "scan": "b", "state": "queued", "waiting_s": 3.0}
    assert worker_state([], [running, queued], now) == {"state": "working", "jobs": ["a-fast"], "queued": 1,
                                                        "workers": []}
    assert worker_state([], [{**running, "stale": "worker x pid 1 died mid-job"}], now) == {
        "state": "gone", "jobs": ["a-fast"], "workers": []}
    assert worker_state([], [queued], now)["state"] == "queued"  # a worker takes it at its next look
    assert worker_state([], [{**queued, "waiting_s": LOOK_S}], now)["state"] == "untaken"
    done = ScanRow("done", "complete", mtime=now - 10 * LOOK_S)
    fresh = ScanRow("fresh", "complete", mtime=now - 1.0)  # just finished: no worker has had its look yet
    recording = ScanRow("rec", "running", mtime=now - 10 * LOOK_S)  # a worker without --live leaves it
    assert worker_state([done, fresh, recording], [], now) == {"state": "unqueued", "scans": ["done"],
                                                               "waited_s": 10 * LOOK_S, "workers": []}
    finished = {"id": "done-fast", "scan": "done", "state": "done"}
    assert worker_state([done, fresh, recording], [finished], now) == {"state": "none", "workers": []}
    present = [{"host": "lab", "pid": 7}, {"host": "gpu", "pid": 9}]
    assert worker_state([done, fresh, recording], [finished], now, present) == {
        "state": "waiting", "workers": ["lab pid 7", "gpu pid 9"]}
