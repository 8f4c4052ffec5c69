"""The `ctl wait` progress bar tells the truth about rate and time left: none while the scan is paused (a pause has
no end time), a rate of the poses it saw taken (not of those published before the wait began), and no pause counted
into the rate after a resume. tqdm's clock is a fake one the tests move on, so nothing depends on wall-clock luck."""

from __future__ import annotations

import io
import re

import pytest
import tqdm.std

from spadscan.commands.ctl import ProgressBar


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


class Clock:
    """tqdm's time, moved on by the test."""

    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock(monkeypatch):
    fake = Clock()
    monkeypatch.setattr(tqdm.std, "time", fake)  # tqdm reads its clock through this name when a bar is made
    monkeypatch.setattr(tqdm.std.tqdm, "monitor_interval", 0)  # no monitor thread left behind
    return fake


def shown(stream: Terminal) -> str:
    """The bar as the terminal shows it now (its last redraw)."""
    return stream.getvalue().split("\r")[-1].strip()


def status(state: str, pose: int, reason: str | None = None) -> dict:
    return {"scan": "goblet", "state": state, "pose": pose, "poses": 48, "reason": reason}


def watched(clock: Clock, statuses) -> str:
    """The bar as shown after `wait` polled each status in turn, a second apart."""
    stream = Terminal()
    bar = ProgressBar("goblet", stream)
    try:
        for polled in statuses:
            bar.update(polled)
            clock.t += 1.0
        return shown(stream)
    finally:
        bar.close()


def rate_of(line: str) -> float:
    """The poses per second the bar shows (tqdm writes a slow rate as seconds per pose)."""
    found = re.search(r"([\d.]+)(pose/s|s/pose)", line)
    assert found, line
    return float(found.group(1)) if found.group(2) == "pose/s" else 1.0 / float(found.group(1))


@pytest.mark.parametrize("state,reason", [("paused", "sensor silent: no complete frame within 5 s at pose 20"),
                                          ("pausing", None)])
def test_a_scan_that_is_not_scanning_shows_no_rate_and_no_time_left(clock, state, reason):
    line = watched(clock, [status(state, 20, reason)] * 4)  # `wait` polls the status; the scan stays where it is
    assert "20/48" in line and f"[{state}" in line, line
    assert "pose/s" not in line and "<" not in line, line  # no rate, no time left


def test_a_wait_begun_mid_scan_counts_only_the_poses_it_saw_taken(clock):
    # 20 poses published before the wait; then 2 a second
    line = watched(clock, [status("scanning", pose) for pose in (20, 22, 24, 26)])
    assert "26/48" in line, line
    assert rate_of(line) == pytest.approx(2.0, abs=0.01), line
    assert "<00:11," in line, line  # 22 poses left at 2 a second


def test_a_pause_is_not_counted_into_the_rate_after_the_resume(clock):
    line = watched(clock, [status("scanning", pose) for pose in (10, 12, 14, 16)]
                   + [status("paused", 16, "paused by user")] * 30  # paused 30 s by the operator
                   + [status("scanning", pose) for pose in (16, 18, 20, 22)])  # resumed: 2 poses a second again
    assert "22/48" in line, line
    assert rate_of(line) == pytest.approx(2.0, abs=0.01), line
    assert "<00:13," in line, line  # 26 poses left at 2 a second
    assert "[00:06<" in line, line  # the time spent scanning while watched: 3 s, then 3 s after the resume


def test_the_reason_is_shown_as_it_is_even_with_braces(clock):
    stream = Terminal()
    bar = ProgressBar("goblet", stream)
    try:
        bar.update(status("paused", 5, "cannot reopen the capture: {odd} 100%"))
        line = shown(stream)
    finally:
        bar.close()
    assert "[paused: cannot reopen the capture: {odd} 100%]" in line, line


def test_a_complete_scan_fills_the_bar(clock):
    stream = Terminal()
    bar = ProgressBar("goblet", stream)
    try:
        bar.update(status("scanning", 46))
        clock.t += 1.0
        bar.finish("complete")
    finally:
        bar.close()
    line = shown(stream)
    assert "48/48" in line and "[complete]" in line, line


def _live(tmp_path, state: str, used: int, published: int) -> str:
    """A capture folder whose live status says `state`, `used` views fitted of `published` (as its job last read)."""
    from spadscan.protocol.live_status import LiveStatus, status_path, write_status

    folder = status_path(tmp_path / "goblet").parent
    folder.mkdir(parents=True)
    write_status(folder, LiveStatus(views_used=used, views_published=published, steps=300, converged=False,
                                    state=state, views_planned=48, job="q1-live"))
    return str(tmp_path / "goblet")


@pytest.mark.parametrize("state, behind", [("live", True), ("final", False)])
def test_a_live_fit_behind_the_scan_says_how_many_views_the_scan_has_published(clock, tmp_path, state, behind):
    """The live status counts the views its job last read (26/26): the bar also names the scan's own count (40), as
    the dashboard's "fit of 26 of 40 views" does; a final run fits every view, and says nothing of the kind."""
    path = _live(tmp_path, state, 26, 26)
    said = watched(clock, [{**status("scanning", 40), "path": path}])
    assert "26/26 views" in said
    assert ("the scan has published 40 views" in said) == behind
