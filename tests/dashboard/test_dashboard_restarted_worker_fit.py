"""A worker restarted after its live job's worker died takes the job over and gives it back to the queue: the live
status keeps the dead attempt's figures (views, steps, Chamfer) until the next attempt writes its own, but is written
anew, so that its update time is the give-back's. Neither the dashboard nor `spadscan ctl status` shows that Chamfer
as the job's now: each says it is the stopped attempt's, as of the time it was measured."""

from __future__ import annotations

import datetime as _dt
import json
import subprocess
import sys

from dashboard_helpers import serving
from page_helpers import add_pose, browser_page, start_scan
from spadscan.commands.ctl import capture_live, live_line
from spadscan.dashboard.server import address
from spadscan.protocol.live_status import read_status, status_path
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job
from spadscan.worker.live.done import mark_live_queued
from spadscan.worker.queue import Queue

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine


def dead_workers_live_job(root, measured: _dt.datetime) -> None:
    """Scan vase in hand; its live job's worker died (its process is gone) after its last status (4 min ago)."""
    writer, poses = start_scan(root / "vase", 64)
    for i in range(3):
        add_pose(writer, poses, i)
    live = root / "vase" / "recon" / "live"
    live.mkdir(parents=True)
    (live / "status.json").write_text(json.dumps(
        {"views_used": 33, "views_published": 40, "steps": 136, "chamfer_mm": 39.1556, "state": "live",
         "job": "vase-fast", "updated_utc": measured.isoformat()}))
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    queue = Queue.for_root(root)
    queue.enqueue(Job(id="vase-fast", scan="vase", live=True))
    queue.claim(Holder(**{**Holder.current().to_dict(), "pid": gone.pid, "pid_start": ""}))


def restarted_worker_takes_it_over(root) -> None:
    """What a worker started on the root does first (pool.py `_take_over`): the dead worker's job back to the queue,
    its live status saying so (`mark_live_queued`) while the worker holds it."""
    queue = Queue.for_root(root)
    taken = queue.reclaim_expired(before_requeue=lambda job, why: mark_live_queued(job, root, why, print))
    assert taken == [("vase-fast", "queued")], taken


def test_a_restarted_workers_live_line_marks_the_dead_fits_chamfer_with_its_time(tmp_path):
    measured = _dt.datetime.now(_dt.timezone.utc) - _dt.timedelta(minutes=4)
    at = measured.strftime("%Y-%m-%d %H:%M:%S") + " UTC"
    dead_workers_live_job(tmp_path, measured)
    restarted_worker_takes_it_over(tmp_path)
    status = read_status(status_path(tmp_path / "vase"))
    assert status.state == "queued" and status.chamfer_mm == 39.1556
    assert status.figures_utc == measured.isoformat(), "the figures keep the time they were measured at"
    line = live_line(capture_live(str(tmp_path / "vase"), str(tmp_path)))
    assert "the stopped attempt's 33/40 views, 136 steps, Chamfer 39.16 mm (as of " + at in line, line
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        pick = page.locator('#scans tr[data-scan="vase"] a.pick')
        pick.wait_for(timeout=WAIT_MS)
        said = pick.text_content()
        assert said.startswith("live, queued again (the stopped attempt's fit as of " + at + ", 4 min ago: 33 views, "
                               "136 steps), its Chamfer against the ground truth on its 33 views: 39.16 mm"), said
        assert "the live fit's Chamfer" not in page.locator("body").inner_text()
    assert not seen.errors, seen.errors
