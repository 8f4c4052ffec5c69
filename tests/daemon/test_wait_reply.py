"""The daemon's `wait` reply describes the scan waited for, from the runner's own record of how each scan ended:
`ctl wait --json` prints the daemon's status as that scan ended (not a status read afterwards, by when the next scan
may run), and the reply's `reason` is the one the runner ended the scan with, whatever its folder says by the time the
reply is made (a folder deleted by hand says nothing). A scan ended before the daemon started is read from its
folder."""

from __future__ import annotations

import asyncio
import json

from spadscan.cli import main
from spadscan.daemon.app import Dispatcher
from spadscan.daemon.control import ControlServer
from spadscan.protocol.live_status import LiveStatus, write_status

from test_runner import daemon_runner, make_cfg, paused_after, sphere, until  # noqa: F401  (sphere: a fixture)
from test_runner_operator import delete_by_hand


def live_of(capture, job: str) -> None:
    """A live reconstruction's status in `capture`, of job `job`."""
    (capture / "recon" / "live").mkdir(parents=True)
    write_status(capture / "recon" / "live", LiveStatus(views_used=4, views_published=4, steps=10, state="final",
                                                        job=job))


def test_wait_json_describes_the_scan_waited_for_though_the_next_one_runs(arun, tmp_path, sphere, capsys):  # noqa: F811
    """The next scan starts as the wait for the first is answered (before `ctl` could read the daemon's status):
    the line is still the status as the first ended, with the first's live reconstruction. Before: the status read
    after the wait, which named the second scan, scanning, and gave its live reconstruction."""
    cfg = make_cfg(tmp_path, views=4)
    socket = str(cfg.socket)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            dispatch = Dispatcher(runner, asyncio.Event(), cfg)

            async def handler(request: dict) -> dict:
                reply = await dispatch(request)
                if request["op"] == "wait" and request["name"] == "first":
                    await runner.start("second")  # the next scan, queued by the operator, starts at once
                    live_of(runner.job.path, "second-fast")
                    await runner.pause()  # (held: its status must not change before `ctl` reads it)
                return reply

            async with ControlServer(socket, handler):
                await runner.start("first")
                live_of(runner.job.path, "first-fast")
                code = await asyncio.to_thread(main, ["ctl", "--socket", socket, "wait", "first", "--json"])
                now = await dispatch({"op": "status"})
                await runner.abort()
        return code, now

    code, now = arun(scenario())
    out, err = capsys.readouterr()
    assert code == 0 and err == "", err
    line = json.loads(out)
    assert now["scan"] == "second", "the daemon holds the next scan meanwhile"
    assert line["wait"]["name"] == "first" and line["wait"]["ended"] == "complete", line
    assert line["state"] == "idle" and line["scan"] is None, line
    assert line["last_scan"] == {"name": "first", "state": "complete"}, line
    assert line["live"]["job"] == "first-fast", line["live"]
    assert line["daemon"]["captures"] == str(cfg.captures) and line["daemon"]["uptime_s"] <= now["daemon"]["uptime_s"]


def test_plain_wait_prints_the_reply_without_the_status(arun, tmp_path, sphere, capsys):  # noqa: F811
    cfg = make_cfg(tmp_path, views=3)
    socket = str(cfg.socket)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            async with ControlServer(socket, Dispatcher(runner, asyncio.Event(), cfg)):
                await runner.start("plain")
                return await asyncio.to_thread(main, ["ctl", "--socket", socket, "wait", "plain"])

    assert arun(scenario()) == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == {"name": "plain", "state": "complete"} and err == "", (out, err)


def test_the_wait_reply_gives_the_abort_reason_of_a_scan_whose_folder_was_deleted(arun, tmp_path, sphere):  # noqa: F811
    """The operator deletes the paused scan's folder, then aborts it with a reason: the runner knows why it ended,
    the folder (gone) does not. Before: the reply's reason was read back from the folder, and was missing."""
    cfg = make_cfg(tmp_path, views=10)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "gone", runner.pause, "the operator's pause")
            delete_by_hand(runner.job.path)
            await runner.abort("wrong object on the table")
            return await Dispatcher(runner, asyncio.Event(), cfg)({"op": "wait", "name": "gone"})

    waited = arun(scenario())
    assert waited["name"] == "gone" and waited["state"] == "aborted", waited
    assert waited["reason"] == "wrong object on the table", waited
    assert waited["status"]["last_scan"] == {"name": "gone", "state": "aborted"}, waited


def test_a_scan_ended_before_the_daemon_started_is_read_from_its_folder(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=10)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("early")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            await runner.abort("lamp changed")
        async with daemon_runner(cfg, sphere) as later:
            return await Dispatcher(later, asyncio.Event(), cfg)({"op": "wait", "name": "early"})

    waited = arun(scenario())
    assert waited == {"name": "early", "state": "aborted", "reason": "lamp changed", "status": None}, waited
