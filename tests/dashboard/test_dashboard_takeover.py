"""A live job taken over by another attempt: until the new attempt writes its first live status (its process starts,
imports, clears the earlier attempt's mesh and preview), the live folder still holds the earlier attempt's figures and
pictures. The dashboard shows none of them as the running attempt's."""

from __future__ import annotations

import datetime as _dt
import json
import subprocess
import sys

import trimesh

from dashboard_helpers import preview_png, serving, status
from page_helpers import add_pose, browser_page, start_scan
from spadscan.dashboard.server import address
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine
EARLIER = {"views_used": 33, "views_published": 40, "steps": 136, "chamfer_mm": 39.1556, "job": "vase-fast"}


def utc(seconds_from_now: float) -> str:
    return (_dt.datetime.now(_dt.timezone.utc) + _dt.timedelta(seconds=seconds_from_now)).isoformat()


def earlier_attempts_fit(scan, state: str, note: str | None = None) -> None:
    """The live folder as the earlier attempt (and the worker that gave its job back) left it."""
    live = scan / "recon" / "live"
    live.mkdir(parents=True, exist_ok=True)
    trimesh.creation.icosphere(subdivisions=1, radius=0.05).export(live / "mesh.ply")
    (live / "preview.png").write_bytes(preview_png())
    (live / "status.json").write_text(json.dumps({**EARLIER, "state": state, "note": note, "updated_utc": utc(-5)}))


def taken_over(root) -> None:
    """Job vase-fast's first attempt died (its worker's process is gone); a worker took the job over: a new claim,
    whose process has not written the live status yet."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    queue = Queue.for_root(root)
    queue.enqueue(Job(id="vase-fast", scan="vase", live=True))
    queue.claim(Holder(**{**Holder.current().to_dict(), "pid": gone.pid, "pid_start": ""}))
    assert queue.reclaim_expired() == [("vase-fast", "queued")]
    assert queue.claim(Holder.current()) is not None


def scan_in_hand(root) -> None:
    writer, poses = start_scan(root / "vase", 64)
    for i in range(3):
        add_pose(writer, poses, i)


def test_the_answer_marks_the_earlier_attempts_live_fit_and_links_none_of_its_pictures(tmp_path):
    for state in ("live", "queued", "final"):
        root = tmp_path / state
        scan_in_hand(root)
        earlier_attempts_fit(root / "vase", state)
        with serving(root) as server:
            (live,) = status(server)["scans"][0]["recons"]
            assert "earlier_attempt" not in live, "no takeover yet: the fit is its running attempt's"
            taken_over(root)
            (live,) = status(server)["scans"][0]["recons"]
            assert live["earlier_attempt"] is True, state
            assert not {"preview.png", "mesh.ply", "view3d.html"} & set(live["files"]), state
            assert "views_used" not in live["summary"] and "chamfer_mm" not in live["summary"], state


def test_the_page_shows_no_figures_or_pictures_of_the_attempt_before_a_takeover(tmp_path):
    scan_in_hand(tmp_path)
    earlier_attempts_fit(tmp_path / "vase", "queued", note="its worker died; the job is back in the queue")
    taken_over(tmp_path)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        pick = page.locator('#scans tr[data-scan="vase"] a.pick')
        pick.wait_for(timeout=WAIT_MS)
        assert pick.text_content() == "live, starting again (the earlier attempt's fit is not shown)"
        page.wait_for_function("() => document.querySelector('#viewer-name').textContent.includes('starting')",
                               timeout=WAIT_MS)
        assert "33 views" not in page.locator("body").inner_text()
        assert "39.16" not in page.locator("body").inner_text()
        assert page.locator("#viewer-preview").is_hidden() and page.locator("#viewer-3d").is_hidden()
        # the new attempt's first word: its own status, written after its claim
        (tmp_path / "vase" / "recon" / "live" / "status.json").write_text(json.dumps(
            {"views_used": 0, "views_published": 3, "steps": 0, "state": "waiting", "job": "vase-fast",
             "updated_utc": utc(+1)}))
        page.wait_for_function(
            "() => document.querySelector('#scans tr[data-scan=\"vase\"] a.pick').textContent === "
            "'live, waiting for views'", timeout=WAIT_MS)
    assert not seen.errors, seen.errors
