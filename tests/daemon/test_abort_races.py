"""An acknowledged abort stays an abort whatever arrives meanwhile: a `ctl resume NAME` of the same interrupted scan
(one of the two is refused, never both carried out), a SIGTERM while `ctl abort` waits for the arm to stop. A scan
that could not be taken over stays named in status until it is itself resumed or aborted, and the last_error of an
abort the disk could not take says where it stands now. Each interleaving is forced with hooks, not timing."""

from __future__ import annotations

import asyncio
import errno
import json
import shutil
import threading

import pytest

from spadscan.daemon import abort_book
from spadscan.daemon import runner as runner_module
from spadscan.daemon import scan_job
from spadscan.daemon.app import DeviceSession
from spadscan.daemon.runner import ScanRunner
from spadscan.daemon.scan_job import ABORT_PENDING
from spadscan.protocol.errors import ConfigError

from test_abort_durable import disk, manifest  # noqa: F401  (disk: the fixture)
from test_runner import (check_capture, daemon_runner, make_cfg, make_rig, until,  # noqa: F401
                         sphere)  # (sphere: the fixture)
from test_takeover_damaged import interrupted, restarted as recovered, tear

VIEWS = 10


async def restarted(cfg, sphere, then) -> object:  # noqa: F811
    """A daemon on cfg recovers; `then(runner)` runs before it stops and its result is returned."""
    return await recovered(cfg, sphere, lambda runner, status: then(runner))


def held_in_thread(monkeypatch, name: str, module=runner_module) -> tuple[threading.Event, threading.Event]:
    """Make module.`name` (a function run on a thread) wait at its start: returns (entered, release)."""
    entered, release = threading.Event(), threading.Event()
    real = getattr(module, name)

    def held(*args, **kwargs):
        entered.set()
        release.wait(timeout=30.0)
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, held)
    return entered, release


def test_a_resume_that_arrives_while_an_abort_is_written_cannot_undo_it(arun, tmp_path, sphere,  # noqa: F811
                                                                        monkeypatch):
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = tmp_path / "caps" / "vase"
    arun(interrupted(cfg, sphere, "vase"))
    damaged = tear(folder)
    reading = threading.Event()  # a takeover has got as far as reading the scan (the start-up's read is before)

    async def then(runner):
        writing, release = held_in_thread(monkeypatch, "_write_abort", abort_book)
        real_load = runner_module.load_job
        monkeypatch.setattr(runner_module, "load_job", lambda *a, **k: reading.set() or real_load(*a, **k))
        shutil.move(folder / damaged, tmp_path / damaged)  # the operator moved the damaged chunk out
        try:
            abort = asyncio.ensure_future(runner.abort("wrong object", name="vase"))
            await until(writing.is_set, "the abort's write begun")
            resume = asyncio.ensure_future(runner.resume("vase"))
            await until(lambda: resume.done() or reading.is_set(), "the resume refused, or reading the scan")
        finally:
            release.set()
        replies = await asyncio.gather(abort, resume, return_exceptions=True)
        with pytest.raises(ConfigError) as later:
            await runner.resume("vase")
        return replies, runner.status(), str(later.value)

    (aborted, refused), status, later = arun(restarted(cfg, sphere, then))
    assert not reading.is_set()
    assert aborted["aborted"] == "vase" and aborted["abort_recorded"] is True, aborted
    assert isinstance(refused, ConfigError), refused
    assert str(refused) == "an interrupted scan is being aborted; try again in a moment", refused
    assert status["state"] == "idle" and status["scan"] is None, status
    assert status["last_scan"] == {"name": "vase", "state": "aborted"} and "cannot_take_over" not in status
    assert later == "scan 'vase' has already ended (aborted)", later
    assert manifest(folder)["state"] == "aborted" and manifest(folder)["reason"].startswith("wrong object; ")


def test_an_abort_that_arrives_while_a_resume_takes_the_scan_over_is_refused(arun, tmp_path, sphere,  # noqa: F811
                                                                             monkeypatch):
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = tmp_path / "caps" / "vase"
    arun(interrupted(cfg, sphere, "vase"))
    damaged = tear(folder)

    async def then(runner):
        reading, release = held_in_thread(monkeypatch, "load_job")  # (the start-up's read is before)
        shutil.move(folder / damaged, tmp_path / damaged)
        try:
            resume = asyncio.ensure_future(runner.resume("vase"))
            await until(reading.is_set, "the takeover reading the scan")
            with pytest.raises(ConfigError) as refused:
                await runner.abort("wrong object", name="vase")
        finally:
            release.set()
        resumed = await resume
        return str(refused.value), resumed, await runner.wait("vase")

    refused, resumed, done = arun(restarted(cfg, sphere, then))
    assert refused == "an interrupted scan is being taken over; try again in a moment", refused
    assert resumed["state"] == "scanning" and resumed["scan"] == "vase", resumed
    assert done == {"name": "vase", "state": "complete"}
    check_capture(folder, VIEWS, 2)


@pytest.mark.parametrize("cut", ["while the arm stops", "at the request's first turn"])
def test_a_sigterm_during_ctl_abort_does_not_undo_the_abort(arun, tmp_path, sphere, cut):  # noqa: F811
    """ControlServer.close cancels the `ctl abort` handler on SIGTERM, then the runner shuts down: the scan must end
    aborted, and a daemon restarted with auto_resume must not move the arm for it."""
    cfg = make_cfg(tmp_path, views=VIEWS, auto_resume=True)
    folder = tmp_path / "caps" / "s"

    async def scenario():
        arm, sensor = make_rig(cfg, sphere, motion_time_s=0.01)
        stopping, stood = asyncio.Event(), asyncio.Event()
        real_stop = arm.stop

        async def slow_stop():  # a real UR: stopL, then the wait for the arm to stand still
            stopping.set()
            await stood.wait()
            await real_stop()

        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                await runner.start("s")
                await until(lambda: runner.job.next_pose >= 2, "two poses")
                arm.stop = slow_stop
                handler = asyncio.ensure_future(runner.abort("wrong object"))
                if cut == "while the arm stops":
                    await stopping.wait()
                else:  # one turn of the loop: the handler has run its first step, up to its first wait
                    await asyncio.sleep(0)
                handler.cancel()
                await asyncio.gather(handler, return_exceptions=True)
            finally:
                stood.set()
                await runner.shutdown()

    arun(scenario())
    m = manifest(folder)
    assert m["state"] == "aborted" and m["reason"] == "wrong object", m
    status = arun(restarted(cfg, sphere, status_of))
    assert status["state"] == "idle" and status["scan"] is None, status


async def status_of(runner: ScanRunner) -> dict:
    return runner.status()


def test_a_takeover_of_another_scan_keeps_the_one_that_could_not_be_taken_over_named(arun, tmp_path,
                                                                                     sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=VIEWS)
    arun(interrupted(cfg, sphere, "old"))
    arun(interrupted(cfg, sphere, "vase"))
    old = tmp_path / "caps" / "old" / "scan.json"  # 'old' was updated first, to the second: the start-up takes 'vase'
    old.write_text(json.dumps({**json.loads(old.read_text()), "updated_utc": "2000-01-01T00:00:00Z"}))
    tear(tmp_path / "caps" / "vase")

    async def then(runner):
        stuck = runner.status()
        await runner.resume("old")
        await runner.wait("old")
        after = runner.status()
        with pytest.raises(ConfigError) as abort:
            await runner.abort()
        with pytest.raises(ConfigError) as resume:
            await runner.resume()  # tries 'vase' again, still damaged
        return stuck, after, str(abort.value), str(resume.value)

    stuck, after, abort, resume = arun(restarted(cfg, sphere, then))
    assert stuck["cannot_take_over"]["scan"] == "vase", stuck
    assert after["last_scan"] == {"name": "old", "state": "complete"}, after
    assert after["cannot_take_over"] == stuck["cannot_take_over"], after
    assert after["last_error"] == stuck["last_error"] == stuck["cannot_take_over"]["error"], after
    assert abort.endswith("scan 'vase' could not be taken over: `spadscan ctl abort vase` ends it"), abort
    assert resume.startswith("cannot take over interrupted scan 'vase': "), resume
    assert manifest(tmp_path / "caps" / "vase")["state"] == "running"


def test_the_last_error_of_an_unrecorded_abort_says_where_it_stands_after_a_retry(  # noqa: F811
        arun, tmp_path, sphere, disk, monkeypatch):
    """Not even abort-pending.json fits at the abort; the disk then goes read-only (another error), then an empty
    file fits again and a retry makes abort-pending.json: last_error follows each change."""
    monkeypatch.setattr(abort_book, "ABORT_RETRY_S", 3600.0)  # the retries are the ones run below, per request
    fits = {"marker": False}
    real_note = scan_job.note_abort_pending
    monkeypatch.setattr(abort_book, "note_abort_pending", lambda path, reason: fits["marker"] and
                        real_note(path, reason))
    cfg = make_cfg(tmp_path, views=VIEWS, auto_resume=True)
    folder = tmp_path / "caps" / "s"

    async def scenario():
        arm, sensor = make_rig(cfg, sphere, motion_time_s=0.01)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                await runner.start("s")
                await until(lambda: runner.job.next_pose >= 2, "two poses")
                disk["error"] = errno.ENOSPC
                await until(lambda: runner.state == "paused", "the pause for the full disk")
                reply = await runner.abort()
                disk["error"] = errno.EROFS
                await runner.aborts.retry()  # what the Dispatcher runs before each request
                read_only = runner.status()
                fits["marker"] = True
                await runner.aborts.retry()
                return reply, read_only, runner.status(), (folder / ABORT_PENDING).is_file()
            finally:
                disk["error"] = None
                await runner.shutdown()

    reply, read_only, kept, marker = arun(scenario())
    assert reply["abort_recorded"] is False and "No space left on device" in reply["last_error"], reply
    assert "nothing on disk keeps it" in reply["last_error"], reply
    said = read_only["last_error"]
    assert "write error while recording it: Read-only file system" in said and "nothing on disk keeps it" in said
    said = kept["last_error"]
    assert kept["unrecorded_aborts"]["s"]["kept_on_disk"] is True and marker
    assert said.startswith("scan 's' is aborted, but its scan.json does not say so yet (write error while "), said
    assert f"{ABORT_PENDING} in the scan folder keeps it" in said and "scans on by itself" not in said, said
    assert manifest(folder)["state"] == "aborted"  # landed at shutdown, the disk writable again


def same_turn_as_state_reply(runner: ScanRunner, when, request) -> dict:
    """Deliver the arm's state reply and `request()` (a control request: abort, shutdown) in one turn of the loop,
    as two socket reads from one select() are, the first time the scan task reads the arm's state with when(runner)
    true. The scan task then wakes into its own end-check (`_check_end`) as the request's cancellation is under way.
    Returns {"request": the request's future, once sent}."""
    real, out = runner.arm.state, {}

    async def state():
        got = await real()
        if "request" in out or not when(runner):
            return got
        loop = asyncio.get_running_loop()
        reply = loop.create_future()

        def both():
            out["request"] = asyncio.ensure_future(request())  # its first step runs first: it asks the task to end
            reply.set_result(got)

        loop.call_soon(both)
        return await reply

    runner.arm.state = state
    return out


def capturing(pose_of):
    """when(runner): the arm's state read after the frames of a pose (`pose_of(runner)` says whether the pose in
    flight is the one): the read that `_check_end` follows."""
    return lambda runner: (runner.job is not None and runner.job.in_flight is not None
                           and pose_of(runner, runner.job.in_flight))


@pytest.mark.parametrize("where", ["planned pose", "pose taken again"])
def test_an_abort_that_lands_as_the_scan_wakes_into_its_end_check_is_recorded(arun, tmp_path, sphere,  # noqa: F811
                                                                              where):
    """The task begins its wind-down by itself (`_check_end`); the abort's cancellation must not cut it short: the
    reply said the abort is recorded, so scan.json says 'aborted' and the daemon is idle."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    name = "plain" if where == "planned pose" else "vase"
    folder = tmp_path / "caps" / name
    if where == "pose taken again":
        arun(interrupted(cfg, sphere, name))
        moved = tear(folder, 1)
        shutil.move(folder / moved, tmp_path / moved)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            if where == "planned pose":
                sent = same_turn_as_state_reply(runner, capturing(lambda r, i: i == 3), runner.abort)
                await runner.start(name)
            else:
                await runner.recover()
                sent = same_turn_as_state_reply(runner, capturing(lambda r, i: i < r.job.next_pose), runner.abort)
                await runner.resume()
            await until(lambda: "request" in sent, "the abort sent")
            reply = await sent["request"]
            return reply, runner.status()

    reply, status = arun(scenario())
    assert reply["aborted"] == name and reply["abort_recorded"] is True, reply
    assert reply["state"] == status["state"] == "idle" and status["scan"] is None, status
    assert status["last_scan"] == {"name": name, "state": "aborted"}, status
    assert manifest(folder)["state"] == "aborted" and manifest(folder)["reason"] == "aborted by user"


def test_a_shutdown_that_lands_as_a_pausing_scan_wakes_into_its_end_check_leaves_it_paused(arun, tmp_path,
                                                                                          sphere):  # noqa: F811
    """SIGTERM while `ctl pause` waits for the pose in flight: the wind-down records the pause in scan.json, so a
    daemon restarted with auto_resume keeps the scan paused instead of moving the arm by itself. Cut short by the
    shutdown's cancellation, it recorded nothing."""
    cfg = make_cfg(tmp_path, views=VIEWS, auto_resume=True)
    folder = tmp_path / "caps" / "s"

    async def scenario():
        arm, sensor = make_rig(cfg, sphere, motion_time_s=0.01)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            sent = {}
            try:
                sent = same_turn_as_state_reply(runner, capturing(lambda r, i: i == 3 and r.state == "pausing"),
                                                runner.shutdown)
                real_move = arm.move_to

                async def move_to(tcp, speed, accel):
                    if runner.job is not None and runner.job.in_flight == 3 and runner.state == "scanning":
                        await runner.pause()
                    await real_move(tcp, speed, accel)

                arm.move_to = move_to  # the pause is asked for as pose 3's move begins: pose 3 is finished first
                await runner.start("s")
                await until(lambda: "request" in sent, "the shutdown sent")
                await sent["request"]
                return runner.state
            finally:
                if "request" not in sent:
                    await runner.shutdown()

    assert arun(scenario()) == "pausing"
    m = manifest(folder)
    assert m["state"] == "running" and m["paused"]["reason"] == "paused by user", m
    status = arun(restarted(cfg, sphere, status_of))
    assert status["state"] == "paused" and status["scan"] == "s" and status["reason"] == "paused by user", status
