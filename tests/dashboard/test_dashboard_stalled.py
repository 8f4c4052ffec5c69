"""A scan whose scan.json says running but that publishes no new pose (its daemon paused and could not record it, on a
full disk; or it hangs) is shown as stalled, without a frame rate, saying for how long and where to ask why, in
/api/status and on the page; a new pose (a resume) shows it scanning again. Also: the state of the scan in hand is
read in full, the viewer follows the running job when no scan is in hand, and the scans table keeps a bar's count and
a time on one line.

"Old" is made by setting file times (os.utime), never by waiting."""

from __future__ import annotations

import os
import time

from dashboard_helpers import complete_scan, serving, status
from page_helpers import add_pose, browser_page, start_scan
from spadscan.commands.dashboard import daemon_running
from spadscan.daemon.root_lock import RootLock
from spadscan.dashboard.scans import QUIET_FACTOR, QUIET_FLOOR_S, quiet_limit_s
from spadscan.dashboard.server import address
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine
ASK = "`spadscan ctl status` says why"


def recording(path, poses: int, planned: int = 40):
    """A running scan of `planned` poses with `poses` published, 0.25 s apart by their frames' times."""
    writer, plan = start_scan(path, planned)
    for i in range(poses):
        add_pose(writer, plan, i, t_s=10.0 + 0.25 * i)
    return writer, plan


def last_news(scan, seconds_ago: float, gap_s: float = 0.25) -> None:
    """The scan's files as if its last pose was published `seconds_ago`, its poses `gap_s` apart before it, and its
    scan.json last written no later than its first pose."""
    now = time.time()
    chunks = sorted(scan.glob("chunk-*"))
    for k, chunk in enumerate(reversed(chunks)):
        then = now - seconds_ago - k * gap_s
        os.utime(chunk, (then, then))
    then = now - seconds_ago - len(chunks) * gap_s
    os.utime(scan / "scan.json", (then, then))


def test_the_limit_follows_the_scans_own_pace_with_a_floor():
    assert quiet_limit_s([]) == quiet_limit_s([100.0]) == QUIET_FLOOR_S  # no pace yet
    assert quiet_limit_s([100.0, 100.25, 100.5]) == QUIET_FLOOR_S  # a brisk scan: the floor
    assert QUIET_FLOOR_S > 60 + 30, "a healthy pose may take the daemon's whole move timeout and its frames"
    assert quiet_limit_s([0.0, 40.0, 80.0]) == QUIET_FACTOR * 40.0  # a slow one (a pendant slider at 5 %)
    # a pause and resume between two poses does not stretch it: the median gap is the pace
    assert quiet_limit_s([0.0, 40.0, 80.0, 900.0, 940.0]) == QUIET_FACTOR * 40.0


def test_a_running_scan_without_a_new_pose_is_stalled_without_a_frame_rate_until_a_pose_comes(tmp_path):
    writer, plan = recording(tmp_path / "full1", 29)
    with serving(tmp_path) as server:
        last_news(tmp_path / "full1", QUIET_FLOOR_S - 10)  # within the limit: still scanning
        current = status(server)["current"]
        assert (current["state"], current["reason"], current["quiet_s"]) == ("running", None, None)
        assert current["frames_per_s"] > 0
        last_news(tmp_path / "full1", 140)
        st = status(server)
        current = st["current"]
        assert (current["name"], current["state"]) == ("full1", "stalled")
        assert current["reason"] == f"no new pose for 2 min: the daemon may be paused or stuck; {ASK}"
        assert 139 <= current["quiet_s"] <= 149
        assert "frames_per_s" not in current and "poses_per_min" not in current
        assert (current["poses"], current["planned"]) == (29, 40)  # what is on disk is still shown
        (row,) = st["scans"]
        assert (row["state"], row["reason"]) == ("stalled", current["reason"])
        add_pose(writer, plan, 29, t_s=20.0)  # the daemon resumed: a new pose
        current = status(server)["current"]
        assert (current["state"], current["reason"], current["quiet_s"]) == ("running", None, None)
        assert current["frames_per_s"] is None, "one pose since the stop: no pace yet (across the stop it was false)"
        add_pose(writer, plan, 30, t_s=20.5)
        assert status(server)["current"]["frames_per_s"] > 0


def test_a_slow_scan_is_given_several_of_its_pose_intervals_and_a_resume_counts_as_news(tmp_path):
    writer, plan = recording(tmp_path / "slow", 4)
    with serving(tmp_path) as server:
        last_news(tmp_path / "slow", 150, gap_s=40.0)  # a pose every 40 s: 200 s allowed
        assert status(server)["current"]["state"] == "running"
        last_news(tmp_path / "slow", 210, gap_s=40.0)
        assert status(server)["current"]["state"] == "stalled"
        writer.set_state("running")  # a resume rewrites scan.json: the next pose is awaited from there
        assert status(server)["current"]["state"] == "running"


def test_a_daemon_gone_is_said_as_interrupted_not_stalled(tmp_path):
    recording(tmp_path / "s1", 3)
    last_news(tmp_path / "s1", 300)
    with serving(tmp_path, daemon_running=daemon_running) as server:
        current = status(server)["current"]
        assert (current["state"], current["reason"]) == ("interrupted", "no daemon running")


def test_the_page_says_a_stalled_scan_at_the_top_and_in_the_scan_in_hand_in_full(tmp_path):
    writer, plan = recording(tmp_path / "full1", 29)
    with RootLock(tmp_path), serving(tmp_path, daemon_running=daemon_running) as server, \
            browser_page(1280, 700) as (page, seen):
        page.goto(address(server))
        page.wait_for_function("() => document.querySelector('#current-state').textContent === 'scanning'",
                               timeout=WAIT_MS)
        last_news(tmp_path / "full1", 150)
        page.wait_for_function("() => document.querySelector('#current-state').textContent.startsWith('stalled')",
                               timeout=WAIT_MS)
        state = page.locator("#current-state")
        said = state.text_content()
        assert said.startswith("stalled (no new pose for ") and said.endswith(f"{ASK})"), said
        assert state.get_attribute("class") == "state-stalled"
        assert state.evaluate("e => e.scrollWidth <= e.clientWidth && e.scrollHeight <= e.clientHeight"), \
            "the reason is cut"
        assert page.locator("#current-rate").text_content() == page.locator("#current-ppm").text_content() == "-"
        daemon = page.locator("#daemon")
        assert daemon.text_content().startswith(" · daemon: no new pose of full1 for ")
        assert daemon.get_attribute("class") == "down"
        assert daemon.evaluate("e => e.getBoundingClientRect().right <= e.parentElement.getBoundingClientRect().right")
        cell = page.locator('#scans tr[data-scan="full1"] td').nth(1)
        assert cell.text_content() == "stalled"
        assert cell.evaluate("td => getComputedStyle(td).color") == "rgb(187, 0, 0)"  # as errors are
        add_pose(writer, plan, 29, t_s=20.0)  # resumed
        page.wait_for_function("() => document.querySelector('#current-state').textContent === 'scanning'",
                               timeout=WAIT_MS)
        assert daemon.text_content() == " · daemon: scanning full1"
        assert daemon.get_attribute("class") == ""
    assert not seen.errors, seen.errors


def test_the_viewer_follows_the_running_job_when_no_scan_is_in_hand(tmp_path):
    complete_scan(tmp_path / "older", 2)
    then = time.time() - 600
    os.utime(tmp_path / "older" / "scan.json", (then, then))
    complete_scan(tmp_path / "latest", 2)
    queue = Queue.for_root(tmp_path)
    queue.enqueue(Job(id="older-fast", scan="older"))
    queue.claim(Holder.current())  # a worker reconstructs the older scan
    queue.enqueue(Job(id="latest-fast", scan="latest"))  # the latest one waits its turn
    with serving(tmp_path) as server, browser_page() as (page, seen):
        assert status(server)["current"]["name"] == "latest"  # the last scan, in its panel
        page.goto(address(server))
        page.wait_for_function("() => document.querySelector('#viewer-name').textContent !== 'none yet'",
                               timeout=WAIT_MS)
        said = page.locator("#viewer-name").text_content()
        assert said.startswith("older / no result yet: reconstructing"), said
    assert not seen.errors, seen.errors


ONE_LINE_PX = 24  # a line of the table's text is about 17 px high: two are over 30
CONTENT_HEIGHTS = """() => [...document.querySelectorAll('#scans tbody tr')].map(tr => {
    const heights = [...tr.querySelectorAll('td')].slice(2, 4).map(td => {
      const r = document.createRange(); r.selectNodeContents(td); return r.getBoundingClientRect().height; });
    return [tr.dataset.scan, ...heights]; })"""


def test_a_long_reconstructions_cell_does_not_wrap_a_bar_count_or_a_time(tmp_path):
    for i in range(3):
        complete_scan(tmp_path / f"plain{i}", 8)
    complete_scan(tmp_path / "noted", 8)
    final = tmp_path / "noted" / "recon" / "noted-fast"
    final.mkdir(parents=True)
    # a reconstruction label long enough to take the table's width, the other rows' cells empty
    (final / "report.json").write_text('{"preset": "' + "a-long-preset-name " * 30 + '", "chamfer_mm": 2.5}')
    with serving(tmp_path) as server, browser_page(1280, 700) as (page, seen):
        page.goto(address(server))
        page.locator('#scans tr[data-scan="noted"] a.pick').wait_for(timeout=WAIT_MS)
        page.locator('#scans tr[data-scan="plain0"]').wait_for(timeout=WAIT_MS)
        for name, progress_px, updated_px in page.evaluate(CONTENT_HEIGHTS):
            assert progress_px < ONE_LINE_PX and updated_px < ONE_LINE_PX, (name, progress_px, updated_px)
    assert not seen.errors, seen.errors
