"""The dashboard's one line on the reconstruction side, in a real headless browser: it stays one line whatever the
length of the captures root it names (the middle of a long path gives way, the full line in its title, the command
whole in its text), so that the panels below never move; and while the workers wait for room on a full disk it says
so, where the queued jobs and the worker's own line would otherwise read as taken at the next look."""

from __future__ import annotations

import json
import time

import pytest

from dashboard_helpers import serving, status
from page_helpers import add_pose, browser_page, start_scan
from spadscan.dashboard.server import address
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job
from spadscan.worker.presence import start_command
from spadscan.worker.queue import Queue

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine
WINDOW = (1280, 700)  # a 1280x800 browser window less its tab strip and address bar
LONG_ROOT = 118
"""Characters of the long captures root (as an operator's nested project folder on a shared disk)."""

# how many lines the text of an element takes, as laid out (the tops of its text's pieces)
LINES = """(s) => { const walker = document.createTreeWalker(document.querySelector(s), NodeFilter.SHOW_TEXT);
    const tops = new Set();
    while (walker.nextNode()) { const range = document.createRange(); range.selectNodeContents(walker.currentNode);
      for (const r of range.getClientRects()) if (r.width > 0) tops.add(Math.round(r.top)); }
    return tops.size; }"""
TOP = "(s) => document.querySelector(s).getBoundingClientRect().top"
# whether the first occurrence of a text in the element is shown: each of its pieces lies inside the box of the element
# that holds it and of the element itself (neither cut off by an ellipsis nor hidden past the edge)
SHOWN = """([s, text]) => { const e = document.querySelector(s), all = e.textContent, at = all.indexOf(text);
    if (at < 0) return false;
    const inside = (r, b) => r.left >= b.left - 0.5 && r.right <= b.right + 0.5;
    const walker = document.createTreeWalker(e, NodeFilter.SHOW_TEXT); let offset = 0;
    while (walker.nextNode()) {
      const node = walker.currentNode, from = Math.max(at, offset), to = Math.min(at + text.length,
        offset + node.length);
      if (from < to) {
        const range = document.createRange(); range.setStart(node, from - offset); range.setEnd(node, to - offset);
        const rects = [...range.getClientRects()].filter(r => r.width > 0);
        if (!rects.every(r => inside(r, node.parentElement.getBoundingClientRect()) &&
                              inside(r, e.getBoundingClientRect()))) return false;
      }
      offset += node.length;
    }
    return true; }"""


def wait_text(page, selector: str, text: str) -> str:
    page.wait_for_function("([s, t]) => (document.querySelector(s) || {}).textContent?.includes(t)",
                           arg=[selector, text], timeout=WAIT_MS)
    return page.locator(selector).text_content()


def long_root(tmp_path):
    """A captures root whose full path is LONG_ROOT characters long (a skip where the test's folder is longer)."""
    base = tmp_path.resolve() / "lab-scans"
    if len(str(base)) > LONG_ROOT - 13:
        pytest.skip(f"the test's folder {base} is too long for a captures root of {LONG_ROOT} characters")
    root = base / ("x" * (LONG_ROOT - len(str(base)) - 1))
    root.mkdir(parents=True)
    return root


def worker_line(root) -> dict:
    """What the page shows of the worker's line for `root` (a scan being recorded, no worker: the line names the
    command that starts one twice): its text, its title, how many lines it takes, where the panels below it start,
    whether its start and the end of the root's path are shown."""
    writer, poses = start_scan(root / "mug", 10)
    add_pose(writer, poses, 0)
    with serving(root) as server, browser_page(*WINDOW) as (page, seen):
        page.goto(address(server))
        text = wait_text(page, "#worker", "start one with")
        line = {"text": text, "title": page.locator("#worker").get_attribute("title"),
                "lines": page.evaluate(LINES, "#worker"), "main": page.evaluate(TOP, "#main"),
                "start shown": page.evaluate(SHOWN, ["#worker", "no worker is running"]),
                "end shown": page.evaluate(SHOWN, ["#worker", ("/" + root.name)[-12:] + " --live`"])}
    assert not seen.errors, seen.errors
    return line


def test_the_worker_line_stays_one_line_under_a_long_root_and_the_panels_stay_put(tmp_path):
    short = tmp_path / "c"
    short.mkdir()
    shown = {root: worker_line(root) for root in (short, long_root(tmp_path))}
    for root, line in shown.items():
        command = start_command(root, root / ".queue")
        assert command in line["text"] and command in line["title"], "the command is whole, to be copied"
        assert line["lines"] == 1, f"{line['lines']} lines under a root of {len(str(root.resolve()))} characters"
        assert line["start shown"], line["text"]
        assert line["end shown"], f"{root}: the path's last folder is cut off: the middle of the path gives way first"
    (short_line, long_line) = shown.values()
    assert long_line["main"] == short_line["main"], "the panels move with the length of the root"


MOUNT = "/mnt/data"


def room_wait(now: float, **fields) -> dict:
    """A worker's wait for room on a full disk, as its presence file says it (disk_room.RoomWait.note)."""
    return {"mount": MOUNT, "folder": f"{MOUNT}/captures/mug/recon/mug-fast", "free_bytes": 12_000_000,
            "need_bytes": 14_000_000, "since_unix": now, "retry_unix": now + 600.0, "quota": False, **fields}


def present(root, wait: dict | None, token: str = "5eed0001") -> str:
    """A worker (this process) serving `root`, its presence file written by hand, waiting for room where `wait` says
    (None: not waiting); returns its name as the page says it. Renamed into place: the page never reads half a file."""
    holder = Holder.current().to_dict()
    folder = Queue.for_root(root).path / "workers"
    folder.mkdir(exist_ok=True)
    data = {"holder": holder, "root": str(root), "started_unix": time.time(), "processes": 1, "once": False,
            "running": [], "renew_s": 10.0, "token": token, "room_wait": wait}
    temporary = folder / f".{token}.tmp"
    temporary.write_text(json.dumps(data))
    temporary.replace(folder / f"{holder['host']}-{holder['pid']}-{token}.json")
    return f"{holder['host']} pid {holder['pid']}"


def test_workers_waiting_for_room_hold_the_queued_jobs_and_say_where_to_make_it():
    from spadscan.dashboard.worker_state import worker_state

    now = time.time()
    queued = {"id": "mug-fast", "scan": "mug", "state": "queued", "waiting_s": 5.0}
    waiting = {"host": "lab", "pid": 7, "processes": 1, "room_wait": room_wait(now)}
    idle = {"host": "lab", "pid": 8, "processes": 1, "room_wait": None}
    state = worker_state([], [queued], now, [waiting])
    assert state["state"] == "room" and state["jobs"] == ["mug-fast"] and state["workers"] == ["lab pid 7"]
    (wait,) = state["room_waits"]
    assert wait == {**room_wait(now), "worker": "lab pid 7", "free_said": "12 MB", "need_said": "14 MB"}
    # waited long: still the room it waits for, not a worker that leaves it
    assert worker_state([], [{**queued, "waiting_s": 600.0}], now, [waiting])["state"] == "room"
    # another worker takes it at its next look; the one waiting is still said
    both = worker_state([], [queued], now, [waiting, idle])
    assert both["state"] == "queued" and [w["worker"] for w in both["room_waits"]] == ["lab pid 7"]
    assert worker_state([], [], now, [waiting])["state"] == "waiting"  # nothing queued: waiting, and for room
    quota = worker_state([], [queued], now, [{**waiting, "room_wait": room_wait(now, quota=True, free_bytes=None,
                                                                                  need_bytes=None)}])
    assert quota["room_waits"][0]["free_said"] is None and quota["room_waits"][0]["quota"] is True
    for damaged in ({"mount": MOUNT}, "full", room_wait(now, retry_unix=now - 1.0), room_wait(now, free_bytes=-1)):
        state = worker_state([], [queued], now, [{**waiting, "room_wait": damaged}])
        assert state["state"] == "queued" and "room_waits" not in state, damaged


def test_the_page_says_the_workers_wait_for_room_and_not_that_a_worker_takes_the_job_at_its_next_look(tmp_path):
    writer, poses = start_scan(tmp_path / "mug", 10)
    add_pose(writer, poses, 0)
    now = time.time()
    present(tmp_path, room_wait(now))
    room = (f"the worker waits for room on {MOUNT} (12 MB free, 14 MB needed): make room there; it claims again by "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime(now + 600.0))} (sooner once there is room)")
    with serving(tmp_path) as server, browser_page(*WINDOW) as (page, seen):
        page.goto(address(server))
        # nothing queued yet: the worker's wait is the line (worded as `spadscan ctl` words it)
        assert wait_text(page, "#worker", "waits for room") == room
        assert page.locator("#worker").get_attribute("class") == "down"
        Queue.for_root(tmp_path).enqueue(Job(id="mug-fast", scan="mug", live=True))  # the scan's live job
        said = wait_text(page, "#worker", "queued")
        assert said == f"1 job queued: {room}"
        assert status(server)["worker"]["state"] == "room"
        heading = wait_text(page, "#viewer-name", "live reconstruction queued")
        assert heading == f"mug / live reconstruction queued: {room}"
        assert "next look" not in page.locator("body").inner_text()
        present(tmp_path, None)  # room made: the worker says it waits no more
        assert wait_text(page, "#worker", "next look") == "1 job queued: a worker takes it at its next look"
        assert page.locator("#worker").get_attribute("class") == ""
        assert wait_text(page, "#viewer-name", "next look").endswith("a worker takes it at its next look")
    assert not seen.errors, seen.errors
