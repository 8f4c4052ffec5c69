"""The demo's progress line words a live reconstruction's figures as its status's summary does
(`LiveStatus.figures`): a job given back to the queue with no figures yet is not said to hold a stopped attempt's,
and one that has them says they are that attempt's, as of their own time."""

from __future__ import annotations

from spadscan.demo import LiveWatch
from spadscan.protocol.live_status import LiveStatus, status_path, write_status


class Bar:
    def __init__(self):
        self.postfix = None

    def set_postfix_str(self, text: str) -> None:
        self.postfix = text


def watched(tmp_path, status: LiveStatus) -> tuple[str, list[str]]:
    """(the bar's line, the lines said) of a LiveWatch on a capture whose live status is `status`."""
    status_path(tmp_path).parent.mkdir(parents=True)
    write_status(status_path(tmp_path).parent, status)
    said = []
    watch = LiveWatch(tmp_path, said.append)
    watch.bar = Bar()
    assert watch() == status
    return watch.bar.postfix, said


def test_a_job_queued_again_before_any_fit_has_no_stopped_attempts_figures_on_the_bar(tmp_path):
    status = LiveStatus(0, 0, 0, state="queued", updated_utc="2026-12-03T17:30:00Z", job="live-1")
    bar, said = watched(tmp_path, status)
    assert bar == "live: 0/0 views, 0 steps", bar
    assert said == [status.summary()] and "stopped attempt" not in said[0], said


def test_a_job_queued_again_after_a_fit_says_its_figures_are_the_stopped_attempts_as_the_summary_does(tmp_path):
    status = LiveStatus(8, 9, 40, state="queued", updated_utc="2026-12-03T17:30:00Z", job="live-1",
                        views_planned=12, chamfer_mm=1.5, figures_utc="2026-12-03T17:29:55Z")
    bar, said = watched(tmp_path, status)
    assert bar.startswith("live: the stopped attempt's 8/9 views of 12 planned, 40 steps, Chamfer 1.50 mm (as of "
                          "2026-12-03 17:29:55 UTC, "), bar
    assert said[0].startswith("live reconstruction queued again: " + bar.removeprefix("live: ").split(" s ago")[0])
