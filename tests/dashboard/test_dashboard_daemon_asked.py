"""How often the dashboard asks the daemon for its status (`spadscan ctl status` over its socket): at most once a
second after its last answer came, however many pages poll, and by one poll at a time (the others show the last
answer); and the page sends its next poll only once the last one is answered."""

from __future__ import annotations

import threading
import time

from dashboard_helpers import serving
from page_helpers import browser_page
from spadscan.dashboard.server import address
from spadscan.dashboard.status import DAEMON_ASKED_S, Dashboard


def idle(root, n: int) -> dict:
    """The reply of an idle daemon on `root`, numbered by `n` (which answer the dashboard shows)."""
    return {"ok": True, "state": "idle", "scan": None, "last_error": f"answer {n}", "daemon": {"captures": str(root)}}


class Clock:
    def __init__(self):
        self.now = 1_800_000_000.0

    def __call__(self) -> float:
        return self.now


def test_the_daemon_is_asked_once_a_second_however_often_the_page_polls(tmp_path):
    clock, asked = Clock(), []
    dash = Dashboard(tmp_path, daemon_running=lambda r: True, clock=clock,
                     daemon_status=lambda r: asked.append(clock.now) or idle(tmp_path, len(asked)))
    assert dash.status()["daemon_status"]["last_error"] == "answer 1"
    clock.now += DAEMON_ASKED_S / 2
    assert dash.status()["daemon_status"]["last_error"] == "answer 1" and len(asked) == 1
    clock.now += DAEMON_ASKED_S
    assert dash.status()["daemon_status"]["last_error"] == "answer 2" and len(asked) == 2


def test_a_slow_answer_counts_its_second_from_when_it_came(tmp_path):
    clock, asked = Clock(), []

    def slow(root):  # a daemon that takes its whole timeout to answer
        asked.append(clock.now)
        clock.now += 2.0
        return idle(tmp_path, len(asked))

    dash = Dashboard(tmp_path, daemon_running=lambda r: True, clock=clock, daemon_status=slow)
    dash.status()
    clock.now += DAEMON_ASKED_S / 2
    assert dash.status()["daemon_status"]["last_error"] == "answer 1" and len(asked) == 1, asked


def test_one_poll_asks_at_a_time_and_the_others_show_the_last_answer(tmp_path):
    clock, asked, go_on = Clock(), [], threading.Event()

    def held(root):  # answers at once until `go_on` is cleared: then it waits for it (a daemon slow to answer)
        asked.append(clock.now)
        go_on.wait(10)
        return idle(tmp_path, len(asked))

    dash = Dashboard(tmp_path, daemon_running=lambda r: True, clock=clock, daemon_status=held)
    go_on.clear()
    first = [threading.Thread(target=dash.status) for _ in range(4)]  # pages that poll at once, no answer yet
    for t in first:
        t.start()
    deadline = time.monotonic() + 10
    while not asked and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.2)  # the others reach the daemon meanwhile, unless they wait for the first answer
    go_on.set()
    for t in first:
        t.join(10)
    assert len(asked) == 1, asked

    clock.now += 2 * DAEMON_ASKED_S
    go_on.clear()
    asking = threading.Thread(target=dash.status)
    asking.start()
    while len(asked) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    seen = []
    other = threading.Thread(target=lambda: seen.append(dash.status()))
    other.start()
    other.join(5)  # the other poll does not wait for the daemon
    answered = not other.is_alive()
    go_on.set()
    asking.join(10)
    other.join(10)
    assert answered, "a poll waited for the daemon while another poll asked it"
    assert len(asked) == 2 and seen[0]["daemon_status"]["last_error"] == "answer 1", (asked, seen)
    assert dash.status()["daemon_status"]["last_error"] == "answer 2"


def test_the_page_sends_no_poll_while_its_last_one_is_unanswered(tmp_path, monkeypatch):
    answering, most, answered = [0], [0], []
    count = threading.Lock()
    status = Dashboard.status

    def slow(self):  # a server that takes 2.5 poll intervals to answer
        with count:
            answering[0] += 1
            most[0] = max(most[0], answering[0])
        try:
            time.sleep(2.5)
            return status(self)
        finally:
            with count:
                answering[0] -= 1
                answered.append(time.monotonic())

    monkeypatch.setattr(Dashboard, "status", slow)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        page.wait_for_function("() => document.querySelector('#link').textContent.startsWith('updated')",
                               timeout=30_000)
        page.wait_for_timeout(4000)
    assert len(answered) >= 2, answered
    assert most[0] == 1, f"{most[0]} polls were waiting at once"
    assert not seen.errors, seen.errors
