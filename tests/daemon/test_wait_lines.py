"""What `spadscan ctl wait` says on stderr without a terminal: a pause's line gives the way on once (a reason that
names `spadscan ctl resume` or `spadscan ctl abort` gets no second piece of advice), and the line of a scan that
ended aborted gives the abort's reason (`ctl abort --reason`, or the daemon's own), which the daemon's `wait` reply
carries as the daemon that ended the scan recorded it (whether or not the disk could take the abort), or, for a scan
that ended before the daemon started, as its manifest records it."""

from __future__ import annotations

import asyncio
import io

import pytest

from spadscan.cli import main
from spadscan.commands.ctl import PauseNotes
from spadscan.daemon.app import Dispatcher
from spadscan.daemon.control import ControlServer

from test_abort_durable import disk  # noqa: F401  (a fixture)
from test_runner import daemon_runner, make_cfg, sphere, until  # noqa: F401  (sphere: a fixture)
from test_runner_operator import paused_on_a_full_disk

RESUME = "`spadscan ctl resume`"
SUFFIX = f" ({RESUME} continues it)"


@pytest.mark.parametrize("reason, advice", [
    ("disk full while publishing: No space left on device (/c/x); make room on the captures' disk, then "
     "`spadscan ctl resume` (pose 51/128)", ""),
    ("cannot reopen the capture: its folder /c/x is gone; `spadscan ctl abort` ends the scan (pose 3/8)", ""),
    ("sensor silent: no frame", SUFFIX),
    (None, SUFFIX),
])
def test_a_pause_line_gives_the_way_on_once(reason, advice):
    stream = io.StringIO()
    notes = PauseNotes("huge2", stream)
    notes.update({"scan": "huge2", "state": "paused", "progress": "51/128", "reason": reason})
    assert stream.getvalue() == f"spadscan: scan 'huge2' paused at pose 51/128: {reason or 'no reason given'}" \
                                f"{advice}\n", stream.getvalue()


def test_wait_names_the_pause_advice_once_and_the_abort_reason(arun, tmp_path, sphere, monkeypatch,
                                                               capsys):  # noqa: F811
    """A real daemon's scan pauses for the sensor's lost link (its reason says to `spadscan ctl resume` once the
    link is back), then is aborted with a reason while `ctl wait` waits: the pause line says the advice once, the
    end line gives the reason. A daemon started afterwards reads the reason from the capture."""
    monkeypatch.setattr("spadscan.commands.ctl.PROGRESS_POLL_S", 0.01)
    cfg = make_cfg(tmp_path, views=40, frame_timeout_s=0.5)
    socket = str(cfg.socket)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            dispatch = Dispatcher(runner, asyncio.Event(), cfg)
            seen_paused = asyncio.Event()

            async def handler(request: dict) -> dict:
                reply = await dispatch(request)
                if request["op"] == "status" and reply.get("state") == "paused":
                    seen_paused.set()  # (`ctl wait` has read the pause: its line is out)
                return reply

            async with ControlServer(socket, handler):
                await runner.start("huge2")
                waiting = asyncio.ensure_future(asyncio.to_thread(main, ["ctl", "--socket", socket, "wait",
                                                                         "huge2"]))
                await until(lambda: runner.job.next_pose >= 2, "two poses")
                runner.sensor.inject_link_loss(3600.0)
                await until(lambda: runner.state == "paused", "the pause for the lost link")
                await asyncio.wait_for(seen_paused.wait(), 30.0)
                paused = runner.status()
                runner.sensor.end_link_loss()
                await dispatch({"op": "abort", "reason": "lens smudged"})
                code = await waiting
        async with daemon_runner(cfg, sphere) as later:  # another daemon: the capture's manifest tells it
            again = await Dispatcher(later, asyncio.Event(), cfg)({"op": "wait", "name": "huge2"})
        return paused, code, again

    paused, code, again = arun(scenario())
    reason = paused["reason"]
    out, err = capsys.readouterr()
    assert code == 1
    assert RESUME in reason, reason
    assert err.splitlines() == [f"spadscan: scan 'huge2' paused at pose {paused['progress']}: {reason}",
                                "spadscan: scan 'huge2' ended aborted: lens smudged"], err
    assert err.count(RESUME) == 1, err
    assert again == {"name": "huge2", "state": "aborted", "reason": "lens smudged", "status": None}, again


def test_the_wait_reply_gives_the_reason_of_an_abort_the_disk_could_not_take(arun, tmp_path, sphere,
                                                                             disk):  # noqa: F811
    """A full disk: the abort is kept in abort-pending.json, not in scan.json; the wait reply gives its reason, and
    the status as the scan ended."""
    cfg = make_cfg(tmp_path, views=10)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_on_a_full_disk(runner, "full1", disk)
            kept = await runner.abort("lens smudged")
            return kept, await Dispatcher(runner, asyncio.Event(), cfg)({"op": "wait", "name": "full1"})

    kept, waited = arun(scenario())
    assert kept["abort_recorded"] is False, kept
    status = waited.pop("status")
    assert waited == {"name": "full1", "state": "aborted", "reason": "lens smudged"}, waited
    assert status["last_scan"] == {"name": "full1", "state": "aborted"} and status["unrecorded_aborts"], status
