"""The dashboard's queue table in a real headless browser: a running job whose worker died (`stale`) shows no frozen
progress or time left and is not coloured as a running job; a running job whose worker lives shows its progress."""

from __future__ import annotations

import subprocess
import sys

from dashboard_helpers import serving
from page_helpers import browser_page
from spadscan.dashboard.server import address
from spadscan.worker.holder import Holder
from spadscan.worker.job_progress import claim_log
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine
BAR = "reconstruct (fast):  21%|##        | 18/85 s [00:18<01:06, loss=27.3, step=268]\r"
RUNNING_BLUE = "rgb(26, 111, 196)"


def _gone_pid() -> int:
    """The pid of a process that has exited (and been reaped)."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    return gone.pid


def _running(queue: Queue, job_id: str, holder: Holder) -> None:
    """`job_id` claimed by `holder`, its log showing a training bar."""
    queue.enqueue(Job(id=job_id, scan=job_id.split("-")[0]))
    claim = queue.claim(holder)
    assert claim is not None and claim.job.id == job_id
    log = claim_log(queue.path, queue.job_paths()[job_id][1])
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text(BAR)


def test_a_stale_jobs_row_shows_no_frozen_progress_and_is_not_coloured_as_running(tmp_path):
    queue = Queue.for_root(tmp_path)
    _running(queue, "alive-fast", Holder.current())
    _running(queue, "dead-fast", Holder(**{**Holder.current().to_dict(), "pid": _gone_pid(), "pid_start": ""}))
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        rows = {job: page.locator(f'#queue tr[data-job="{job}"] td') for job in ("alive-fast", "dead-fast")}
        rows["dead-fast"].first.wait_for(timeout=WAIT_MS)
        rows["alive-fast"].first.wait_for(timeout=WAIT_MS)
        alive_state, alive_progress = rows["alive-fast"].nth(1), rows["alive-fast"].nth(4)
        assert alive_state.text_content() == "running"
        assert alive_state.evaluate("td => getComputedStyle(td).color") == RUNNING_BLUE
        assert alive_progress.text_content().endswith("[00:18 elapsed, 01:06 left]"), alive_progress.text_content()
        dead_state, dead_progress = rows["dead-fast"].nth(1), rows["dead-fast"].nth(4)
        assert dead_progress.text_content() == "" and dead_progress.locator(".bar").count() == 0, \
            "a dead job's frozen bar and time left"
        assert dead_state.text_content() == "stale"
        assert dead_state.get_attribute("class") == "state-stale"
        assert dead_state.evaluate("td => getComputedStyle(td).color") != RUNNING_BLUE
        assert "died mid-job" in rows["dead-fast"].last.text_content()
    assert not seen.errors, seen.errors
