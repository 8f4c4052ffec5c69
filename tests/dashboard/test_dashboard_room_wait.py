"""A wait for room on a full disk, on the dashboard, in a real headless browser. The page shows the line its server
words as `spadscan ctl` and the worker's own lines word it (disk_room.room_said: `RoomWait.where`, `.figures`,
`when_text`), not a wording of its own; and it says that the queue is held by a full disk where a queued job given back
on one holds every claim (its attempt record's `room`, read as the queue's claim reads it: Queue.room_waits), even
while no worker's presence file says it waits yet (a worker between two looks, one just started, one whose presence
file did not fit on the full disk), and, where no worker is present, that one is to be started. The page's lines are
checked against what `spadscan ctl status` says through its own path (ctl.live_queued on the same queue)."""

from __future__ import annotations

import time

import pytest

import spadscan.worker.disk_room as disk_room
from dashboard_helpers import serving, status
from page_helpers import add_pose, browser_page, start_scan
from spadscan.commands.ctl import live_queued
from spadscan.dashboard.server import address
from spadscan.worker.disk_room import RoomWait, room_said, when_text
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue
from test_dashboard_worker_line import WAIT_MS, WINDOW, present, room_wait, wait_text

MB = 1_000_000


def wait_gone(page, selector: str, text: str) -> str:
    """The element's text once it no longer holds `text`."""
    page.wait_for_function("([s, t]) => !((document.querySelector(s) || {}).textContent || '').includes(t)",
                           arg=[selector, text], timeout=WAIT_MS)
    return page.locator(selector).text_content()


def test_the_page_words_a_workers_wait_as_ctl_and_the_worker_do(tmp_path):
    """Before: the page worded it itself ('room on /mnt/data (12 MB free, it waits for 14 MB): make room there'),
    without the time by which the worker claims again."""
    writer, poses = start_scan(tmp_path / "mug", 10)
    add_pose(writer, poses, 0)
    note = room_wait(time.time())
    present(tmp_path, note)
    said = room_said([note])
    wait = RoomWait.from_note(note)
    assert said == (f"the worker waits for room {wait.where} ({wait.figures}): make room there; it claims again by "
                    f"{when_text(wait.retry_unix)} (sooner once there is room)")
    with serving(tmp_path) as server, browser_page(*WINDOW) as (page, seen):
        page.goto(address(server))
        assert wait_text(page, "#worker", "for room") == said  # idle: the wait alone
        assert status(server)["worker"]["room_said"] == said
        Queue.for_root(tmp_path).enqueue(Job(id="mug-fast", scan="mug", live=True))  # the scan's live job
        assert live_queued(str(tmp_path), "mug")["said"] == said  # one wording: `spadscan ctl status` says the same
        assert wait_text(page, "#worker", "queued") == f"1 job queued: {said}"
        assert wait_text(page, "#viewer-name", "live reconstruction queued") == (
            f"mug / live reconstruction queued: {said}")
        assert "it waits for" not in page.locator("body").inner_text()
    assert not seen.errors, seen.errors


def given_back_on_a_full_disk(root) -> RoomWait:
    """The scan mug's live job, claimed and given back to the queue on a full disk as a worker gives it back: its
    attempt record's `room` the wait it began (on the filesystem that holds `root`, where it wrote its result)."""
    queue = Queue.for_root(root)
    queue.enqueue(Job(id="mug-fast", scan="mug", live=True))
    claim = queue.claim()
    wait = RoomWait.begin(root / "mug" / "recon", held=0, retry_s=600.0, job="mug-fast", roots=queue.roots)
    assert queue.release(claim, "no room left on the disk", outcome="disk_full", room=wait.note())
    assert queue.claim() is None  # the queue's own gate: no claim while the room is missing
    return wait


def test_a_queued_jobs_wait_for_room_is_said_while_no_worker_says_it_waits(tmp_path, monkeypatch):
    """Before: '1 job queued: a worker takes it at its next look', while no claim could succeed."""
    free = {"bytes": 12 * MB}
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: free["bytes"])  # the disk stays full
    writer, poses = start_scan(tmp_path / "mug", 10)
    add_pose(writer, poses, 0)
    wait = given_back_on_a_full_disk(tmp_path)
    present(tmp_path, None)  # the worker serving the root does not (yet) say it waits
    said = (f"no job is claimed while mug-fast waits for room {wait.where} (12 MB free, "
            f"{disk_room.size_text(wait.need)} needed): make room there; a worker claims again by "
            f"{when_text(wait.retry_unix)} (sooner once there is room)")
    with serving(tmp_path) as server, browser_page(*WINDOW) as (page, seen):
        page.goto(address(server))
        assert wait_text(page, "#worker", "for room") == f"1 job queued: {said}"
        assert page.locator("#worker").get_attribute("class") == "down"
        worker = status(server)["worker"]
        assert worker["state"] == "room" and worker["room_holds"] and "room_waits" not in worker
        assert live_queued(str(tmp_path), "mug")["said"] == said  # as `spadscan ctl status` says it
        assert [w["job"] for w in worker["queue_room_waits"]] == ["mug-fast"]
        assert wait_text(page, "#viewer-name", "for room") == f"mug / live reconstruction queued: {said}"
        assert "next look" not in page.locator("body").inner_text()
        free["bytes"] = 10**12  # room made: the queue's gate opens, and the page says the job is taken again
        assert "for room" not in wait_gone(page, "#viewer-name", "for room")
        assert "for room" not in wait_gone(page, "#worker", "for room")
        assert page.locator("#viewer-name").text_content().endswith("a worker takes it at its next look")
    assert not seen.errors, seen.errors


@pytest.mark.parametrize("workers", [0, 1])
def test_the_server_says_a_held_queue_with_or_without_workers(tmp_path, monkeypatch, workers):
    """A queued job's wait holds every claim. With a worker present, the queued jobs are held by room (state 'room'),
    not left untaken by the worker, and the line says the wait. With none, the state stays the one without a worker
    ('untaken'), and the line says to start one (with the dashboard's start command; with `--live` in the line for a
    live job, as `spadscan ctl` says it), then by when a worker claims again. Before: the line never said to start
    one."""
    from spadscan.dashboard.worker_state import worker_state

    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: 12 * MB)
    wait = given_back_on_a_full_disk(tmp_path)
    held = list(Queue.for_root(tmp_path).room_waits())
    queued = {"id": "mug-fast", "scan": "mug", "state": "queued", "waiting_s": 600.0}
    idle = [{"host": "lab", "pid": 8, "processes": 1, "room_wait": None}][:workers]
    start = "spadscan worker --root /caps"
    state = worker_state([], [queued], time.time(), idle, held=held, start=start)
    assert state["state"] == ("room" if workers else "untaken") and state["room_holds"]
    said = (f"no job is claimed while mug-fast waits for room {wait.where} (12 MB free, "
            f"{disk_room.size_text(wait.need)} needed): make room there")
    by = f"; a worker claims again by {when_text(wait.retry_unix)} (sooner once there is room)"
    before = f"; no claim succeeds before {when_text(wait.retry_unix)} (sooner once there is room)"
    if workers:
        assert state["room_said"] == said + by and "live_room_said" not in state
    else:  # no worker to claim: when a claim can succeed at the earliest, once one is started
        assert state["room_said"] == f"{said}; no worker is running: start one with `{start}`{before}"
        assert state["live_room_said"] == f"{said}; no worker is running: start one with `{start} --live`{before}"
    assert state["queue_room_waits"][0]["free_said"] == "12 MB"
    assert "room_said" not in worker_state([], [queued], time.time(), idle)  # no wait: nothing said of room


def test_a_held_queue_with_no_worker_says_to_start_one_on_the_page(tmp_path, monkeypatch):
    """No worker, and the live job of the scan being recorded went back to the queue on a full disk: the top line and
    the scan's heading say the wait and to start a worker, in `spadscan ctl`'s words. Before: the heading said
    'no worker is running: start one with ...' alone, the top line said to start one twice."""
    monkeypatch.setattr(disk_room, "free_bytes", lambda folder: 12 * MB)  # the disk stays full
    writer, poses = start_scan(tmp_path / "mug", 10)
    add_pose(writer, poses, 0)
    given_back_on_a_full_disk(tmp_path)
    ctl = live_queued(str(tmp_path), "mug")["said"]  # what `spadscan ctl status` says of the live job
    assert ctl.startswith("no job is claimed while mug-fast waits for room ")
    with serving(tmp_path) as server, browser_page(*WINDOW) as (page, seen):
        page.goto(address(server))
        worker = status(server)["worker"]
        start = worker["start"]
        assert worker["room_said"] == ctl.replace(f"`{start} --live`", f"`{start}`")
        assert f"no worker is running: start one with `{start} --live`; no claim succeeds before " in ctl
        assert wait_text(page, "#worker", "for room") == f"1 job queued: {worker['room_said']}"
        assert page.locator("#worker").get_attribute("class") == "down"
        assert wait_text(page, "#viewer-name", "for room") == f"mug / live reconstruction queued: {ctl}"
    assert not seen.errors, seen.errors
