"""What an operator misread on the dashboard, in a real headless browser where the page is concerned: a job queued
behind a long one is not said to be left untaken the moment that one ends; a part of the page that fails to draw is
said as such, the rest drawn, not taken for a server that is down; the Reconstruction heading is read in full at
phone width; a running job's loss and Chamfer say what they are; a live job queued while several workers run says
what it waits for; the time left of a scan counts the poses it owes again."""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import shutil
import time

from dashboard_helpers import complete_scan, serving, status
from page_helpers import add_pose, browser_page, start_scan
from spadscan.dashboard.server import address
from spadscan.dashboard.worker_state import LOOK_S
from spadscan.worker.holder import Holder
from spadscan.worker.job_progress import claim_log
from spadscan.worker.jobs import Job
from spadscan.worker.presence import Presence, write_presence
from spadscan.worker.queue import Queue

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine
ELSEWHERE = Holder("gpu-box", 4242)  # a worker on another machine: never judged gone from here, but by its lease
# True where every line of the element shows: the element is what the window shows at each line's centre (not
# clipped by a box that hides or scrolls its overflow, nor beyond the window's edge)
SEEN = """(s) => { const e = document.querySelector(s);
  const rects = [...e.getClientRects()].filter(r => r.width > 0 && r.height > 0);
  return rects.length > 0 && rects.every(r => r.right <= innerWidth + 0.5 && r.left >= -0.5 &&
    e.contains(document.elementFromPoint((r.left + r.right) / 2, (r.top + r.bottom) / 2))); }"""


def wait_text(page, selector: str, text: str) -> str:
    page.wait_for_function("([s, t]) => (document.querySelector(s) || {}).textContent?.includes(t)",
                           arg=[selector, text], timeout=WAIT_MS)
    return page.locator(selector).text_content()


def present(root, holder: Holder, processes: int = 1, running: tuple = (), started: float | None = None) -> None:
    """A worker serving `root`, as its presence file says: its job processes and the jobs they run now."""
    write_presence(Queue.for_root(root).path, Presence(holder.to_dict(), str(root), started or time.time(),
                                                       processes, running=list(running), token=f"{holder.pid:08x}"))


def claimed(root, job_id: str, holder: Holder, live: bool = False, log_text: str | None = None):
    """`job_id` (a job of scan `job_id`'s first part) queued and claimed by `holder`; its log holds `log_text`."""
    queue = Queue.for_root(root)
    queue.enqueue(Job(id=job_id, scan=job_id.rsplit("-", 1)[0], live=live))
    claim = queue.claim(holder)
    assert claim is not None and claim.job.id == job_id
    if log_text is not None:
        log = claim_log(queue.path, claim.path)
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text(log_text)
    return claim


def ended_ago(queue: Queue, job_id: str, seconds: float) -> None:
    """Every attempt of `job_id` began and ended `seconds` ago, as its records say."""
    then = time.time() - seconds
    for path in (queue.path / "attempts" / job_id).glob("*.json"):
        record = json.loads(path.read_text())
        record.update(started_unix=then - 1.0, seconds=1.0, ended_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ",
                                                                                      time.gmtime(then)))
        path.write_text(json.dumps(record))


def test_a_job_queued_behind_a_long_one_is_not_said_untaken_the_moment_that_one_ends(tmp_path):
    me = Holder.current()
    present(tmp_path, me)
    queue = Queue.for_root(tmp_path)
    first = claimed(tmp_path, "a-fast", me)
    queue.enqueue(Job(id="b-fast", scan="b"))
    then = time.time() - 6 * LOOK_S  # b-fast was queued 2 minutes ago, behind a-fast
    os.utime(queue.path / "queued" / "b-fast.json", (then, then))
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        wait_text(page, "#worker", "reconstructing a-fast")
        assert queue.finish(first)  # a-fast ends; the worker takes b-fast at its next look
        assert status(server)["worker"]["state"] == "queued"
        page.wait_for_function("() => !document.querySelector('#worker').textContent.includes('reconstructing')",
                               timeout=WAIT_MS)
        assert page.locator("#worker").text_content() == "1 job queued: a worker takes it at its next look"
        assert page.locator("#worker").get_attribute("class") == ""
        ended_ago(queue, "a-fast", 3 * LOOK_S)  # and it does not: a minute later, that is said
        said = wait_text(page, "#worker", "waited")
        match = re.fullmatch(rf"1 job has waited (\d+) s with no job running and the worker on {me.host} pid "
                             rf"{me.pid} has not taken it: see its terminal", said)
        assert match and 3 * LOOK_S <= int(match[1]) < 6 * LOOK_S, said  # from a-fast's end, not from its queueing
        assert page.locator("#worker").get_attribute("class") == "down"
    assert not seen.errors, seen.errors


def test_a_queued_jobs_wait_counts_from_when_a_worker_could_take_it():
    from spadscan.dashboard.worker_state import worker_state

    now = 1_000_000.0
    queued = {"id": "b-fast", "scan": "b", "state": "queued", "waiting_s": 10 * LOOK_S}
    assert worker_state([], [queued], now, freed_unix=now - 2.0)["state"] == "queued"  # a job ended 2 s ago
    assert worker_state([], [queued], now, freed_unix=now - 2 * LOOK_S) == {
        "state": "untaken", "jobs": ["b-fast"], "waited_s": 2 * LOOK_S, "workers": []}
    assert worker_state([], [queued], now, freed_unix=now - 20 * LOOK_S)["waited_s"] == 10 * LOOK_S  # queued later
    assert worker_state([], [queued], now)["waited_s"] == 10 * LOOK_S  # no claim ever: from its queueing


def test_the_last_claim_change_is_read_from_the_attempt_records(tmp_path):
    from spadscan.dashboard.attempts import last_claim_change

    queue = Queue.for_root(tmp_path)
    assert last_claim_change(queue.path, []) is None
    queue.enqueue(Job(id="a-fast", scan="a"))
    assert last_claim_change(queue.path, ["a-fast"]) is None  # never claimed
    before = time.time()
    claim = queue.claim(Holder.current())
    assert before <= last_claim_change(queue.path, ["a-fast"]) <= time.time()  # its start
    ended_ago(queue, "a-fast", 100.0)
    assert abs(last_claim_change(queue.path, ["a-fast"]) - (time.time() - 100.0)) < 2.0  # its end
    (queue.path / "attempts" / "a-fast" / f"{claim.token}.json").write_text('{"ended_utc": "yesterday"')  # torn
    assert last_claim_change(queue.path, ["a-fast"]) is None


def test_a_part_of_the_status_that_fails_to_draw_is_said_and_the_rest_is_drawn_not_greyed(tmp_path):
    complete_scan(tmp_path / "mug", 2)
    Queue.for_root(tmp_path).enqueue(Job(id="mug-fast", scan="mug"))

    def broken(route):  # a status this page cannot draw: the scan's reconstructions are no list
        answer = route.fetch()
        st = answer.json()
        st["scans"][0]["recons"] = 5
        route.fulfill(response=answer, json=st)

    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.route("**/api/status", broken)
        page.goto(address(server))
        said = wait_text(page, "#draw-error", "failed")
        assert said.startswith("this page failed to draw part of the status: ") and "iterable" in said, said
        assert page.locator("#link").text_content().startswith("updated"), "the server answered: it is not down"
        assert not page.evaluate("() => document.body.classList.contains('offline')"), "greyed as if down"
        assert page.locator("#current-name").text_content() == "mug"  # what could be drawn is
        assert page.locator('#queue tr[data-job="mug-fast"]').count() == 1
        assert wait_text(page, "#worker", "queued").startswith("1 job queued")
        page.unroute("**/api/status")  # a status it can draw: the line goes
        page.wait_for_function("() => document.querySelector('#draw-error').hidden", timeout=WAIT_MS)
        page.locator('#scans tr[data-scan="mug"]').wait_for(timeout=WAIT_MS)
    assert seen.errors and all("iterable" in e for e in seen.errors), seen.errors  # the console has the trace


def test_at_phone_width_the_reconstruction_heading_is_read_in_full(tmp_path):
    writer, poses = start_scan(tmp_path / "live1", 40)
    for i in range(21):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    live = tmp_path / "live1" / "recon" / "live"
    live.mkdir(parents=True)
    then = _dt.datetime.now(_dt.timezone.utc) - _dt.timedelta(seconds=12)
    (live / "status.json").write_text(json.dumps({"views_used": 8, "views_published": 8, "steps": 0,
                                                  "chamfer_mm": 50.1, "state": "live", "job": "live1-fast",
                                                  "updated_utc": then.isoformat()}))
    with serving(tmp_path) as server, browser_page(400, 800) as (page, seen):
        page.goto(address(server))
        heading = wait_text(page, "#viewer-name", "updated")
        assert heading.endswith("s ago"), heading
        page.locator("#viewer").scroll_into_view_if_needed()  # one column: the panel is below the scan in hand
        assert page.evaluate(SEEN, "#viewer-name"), "the heading is cut off at 400 px"
        assert page.locator("#viewer h2").evaluate("e => e.scrollHeight <= e.clientHeight + 1")
        assert page.evaluate("() => document.documentElement.scrollWidth") <= 400
    assert not seen.errors, seen.errors


BAR = ("reconstruct (fast):  58%|#####     | 70/120 s [01:10<00:50, step=140, loss=0.966, chamfer=1.86mm, "
       "scored=at step 71; checkpoint 128-cell mesh; 30k points]\r")
SAID = ("reconstruct (fast): 70/120 s, step 140, loss 0.966 (misfit to the measurements plus smoothness terms; lower "
        "is better), Chamfer to the ground truth 1.86 mm, scored at step 71 of the fit (checkpoint 128-cell mesh; "
        "30k points) [01:10 elapsed, 00:50 left]")
BRIEF = ("reconstruct (fast): 70/120 s, step 140, loss 0.966 (lower is better), Chamfer to the ground truth 1.86 mm "
         "at step 71 [01:10 elapsed, 00:50 left]")  # in the heading, whose box holds three lines


def test_a_running_jobs_loss_and_chamfer_say_what_they_are(tmp_path):
    complete_scan(tmp_path / "jug", 10)
    live = tmp_path / "jug" / "recon" / "live"
    live.mkdir(parents=True)
    (live / "status.json").write_text(json.dumps({"views_used": 9, "views_published": 64, "steps": 120,
                                                  "state": "final", "final_start": "hull", "job": "jug-fast"}))
    claimed(tmp_path, "jug-fast", Holder.current(), live=True, log_text=BAR)
    with serving(tmp_path) as server, browser_page(1280, 700) as (page, seen):
        page.goto(address(server))
        row = page.locator('#queue tr[data-job="jug-fast"] td').nth(4)
        assert wait_text(page, '#queue tr[data-job="jug-fast"]', "loss") and row.text_content() == " " + SAID
        assert wait_text(page, "#viewer-name", "loss") == (
            "jug / live, finishing: the final run on 64 views, from the carved hull (not the live fit), is running: "
            + BRIEF)
        assert page.locator("#viewer h2").evaluate("e => e.scrollHeight <= e.clientHeight + 1"), \
            "the heading overflows its box at 1280 px"
    assert not seen.errors, seen.errors


def test_a_live_job_queued_while_two_workers_run_says_what_it_waits_for(tmp_path):
    me = Holder.current()
    for scan in ("q1", "q3"):
        complete_scan(tmp_path / scan, 2)
    claimed(tmp_path, "q1-fast", me)
    other = claimed(tmp_path, "q3-fast", ELSEWHERE)
    writer, poses = start_scan(tmp_path / "q2", 40)
    for i in range(3):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    queue = Queue.for_root(tmp_path)
    queue.enqueue(Job(id="q2-fast", scan="q2", live=True))
    present(tmp_path, me, 2, running=("q1-fast",), started=time.time() - 60)  # a free job process
    present(tmp_path, ELSEWHERE, 1, running=("q3-fast",))
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        assert wait_text(page, "#viewer-name", "queued") == (
            "q2 / live reconstruction queued: a worker takes it at its next look")
        present(tmp_path, me, 1, running=("q1-fast",), started=time.time() - 60)  # both busy
        assert wait_text(page, "#viewer-name", "waiting") == (
            "q2 / live reconstruction queued: waiting for one of q1-fast, q3-fast to finish (the 2 workers run 2 "
            f"jobs at a time; one more worker, or `--processes 2` for the worker on {me.host} pid {me.pid}, runs 3)")
        assert queue.finish(other)  # gpu-box's job ends: it takes q2-fast at its next look
        present(tmp_path, ELSEWHERE, 1, running=())
        assert wait_text(page, "#viewer-name", "next look") == (
            "q2 / live reconstruction queued: a worker takes it at its next look")
    assert not seen.errors, seen.errors


def owed_capture(root):
    """A running scan of 40 poses with 10 published, one pose a half second, whose pose 3's chunk was moved out
    (damaged): the daemon takes it again before pose 10."""
    writer, poses = start_scan(root / "s1", 40)
    for i in range(10):
        add_pose(writer, poses, i, t_s=10.0 + 0.5 * i)
    shutil.rmtree(root / "s1" / "chunk-000003")
    return root / "s1"


def test_the_time_left_counts_the_poses_owed_again_as_the_daemon_does(tmp_path):
    owed_capture(tmp_path)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        current = status(server)["current"]
        assert (current["poses"], current["planned"], current["owed"]) == (10, 40, 1)
        # the daemon's count (runner.scan_eta_s): the poses planned past the last published one, and those owed again
        assert current["eta_s"] == round(60.0 * (40 - 10 + 1) / current["poses_per_min"], 1)
        page.goto(address(server))
        assert wait_text(page, "#current-poses", "again") == "10 / 40 poses, 1 to take again"
    assert not seen.errors, seen.errors
