"""What the operator is told matches where a scan stands: an abort of a scan whose folder was deleted by hand is
simply done (no disk error, nothing kept), a resume whose cause is known to persist is refused at once with the
cause, a daemon stopped mid-scan says where the scan was left and how it goes on, and a UR arm slowed by the
pendant's speed slider says so in `status` and once in the log."""

from __future__ import annotations

import asyncio
import errno
import logging
import shutil
import time

import pytest

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.runner import ScanRunner
from spadscan.protocol.errors import ConfigError

from test_abort_durable import disk  # noqa: F401  (a fixture)
from test_runner import daemon_runner, make_cfg, paused_after, sphere, until  # noqa: F401  (sphere: a fixture)
from test_runner_ur import controller, quick_rig, ur_config  # noqa: F401  (controller: a fixture)


def delete_by_hand(folder) -> None:
    """`rm -rf` of a scan the daemon is writing: a chunk it renames meanwhile can make one pass miss a file (rm -rf
    says so and the operator runs it again), so it is run until the folder is gone."""
    for _ in range(100):  # a bound, not a wait: one or two passes do it
        shutil.rmtree(folder, ignore_errors=True)
        if not folder.exists():
            return
    raise AssertionError(f"{folder} could not be removed")


def test_aborting_a_scan_whose_folder_was_deleted_is_simply_done(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=10)
    folder = tmp_path / "caps" / "del1"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "del1", lambda: delete_by_hand(folder))
            with pytest.raises(ConfigError) as refused:
                await runner.resume()
            aborted = await runner.abort()
            await runner.aborts.retry()  # what each request runs first
            await runner.start("del2")
            done = await runner.wait("del2")
            return str(refused.value), aborted, done, runner.status()

    refused, aborted, done, status = arun(scenario())
    assert refused.startswith("cannot resume scan 'del1': its folder ") and "is gone" in refused, refused
    assert aborted["aborted"] == "del1" and aborted["abort_recorded"] is True, aborted
    assert aborted["abort_note"] == "its folder is gone: nothing to record", aborted
    assert "unrecorded_aborts" not in aborted and "disk" not in (aborted["last_error"] or ""), aborted
    assert not folder.exists()  # nothing was made again in its place (no abort-pending.json)
    assert done["state"] == "complete"
    assert status["last_error"] is None and "unrecorded_aborts" not in status, status


async def paused_on_a_full_disk(runner, name: str, disk) -> None:
    """Scan `name` until two poses are in, then fill the disk (`disk`: the full-disk fixture) and wait for the
    pause it makes."""
    await paused_after(runner, name, lambda: disk.update(error=errno.ENOSPC), "the pause for the full disk")


def test_an_abort_kept_for_a_full_disk_is_done_once_its_folder_is_deleted(arun, tmp_path, sphere, disk):  # noqa: F811
    cfg = make_cfg(tmp_path, views=10)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_on_a_full_disk(runner, "s1", disk)
            kept = await runner.abort()
            delete_by_hand(tmp_path / "caps" / "s1")  # the operator frees the disk by deleting the scan
            await runner.aborts.retry()
            return kept, runner.status()

    kept, status = arun(scenario())
    assert kept["abort_recorded"] is False and "s1" in kept["unrecorded_aborts"], kept
    assert "unrecorded_aborts" not in status and status["last_error"] is None, status


def test_resume_on_a_disk_still_full_is_refused_with_the_cause(arun, tmp_path, sphere, disk):  # noqa: F811
    cfg = make_cfg(tmp_path, views=8)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_on_a_full_disk(runner, "full1", disk)
            with pytest.raises(ConfigError) as refused:
                await runner.resume()
            still = runner.status()
            disk["error"] = None  # room made: the resume goes on as before
            resumed = await runner.resume()
            return str(refused.value), still, resumed, await runner.wait("full1")

    refused, still, resumed, done = arun(scenario())
    assert refused.startswith("cannot resume scan 'full1': cannot reopen the capture: disk full while reopening"), \
        refused
    assert refused.endswith("make room, then `spadscan ctl resume`"), refused
    assert still["state"] == "paused" and still["reason"].startswith("cannot reopen the capture: disk full"), still
    assert resumed["state"] == "scanning" and done["state"] == "complete"


def test_resume_while_the_sensor_link_is_down_is_refused_with_the_cause(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=8, frame_timeout_s=0.5)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "ln1", lambda: runner.sensor.inject_link_loss(3600.0),
                               "the pause for the lost link")
            with pytest.raises(ConfigError) as refused:
                await runner.resume()
            state = runner.state
            runner.sensor.end_link_loss()  # the link comes back
            await runner.resume()
            return str(refused.value), state, await runner.wait("ln1")

    refused, state, done = arun(scenario())
    assert refused.startswith("cannot resume scan 'ln1': the link to ") and "is down" in refused, refused
    assert state == "paused" and done["state"] == "complete"


@pytest.mark.parametrize("paused", [False, True])
def test_a_daemon_stopped_mid_scan_says_where_the_scan_was_left(arun, tmp_path, sphere, caplog, paused):  # noqa: F811
    caplog.set_level(logging.INFO, logger="spadscan.daemon")
    cfg = make_cfg(tmp_path, views=40)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("cc1")
            await until(lambda: runner.job.next_pose >= 3, "three poses")
            if paused:
                await runner.pause()
                await until(lambda: runner.state == "paused", "the pause")
        return runner.job.next_pose  # (shut down: what the capture holds)

    published = arun(scenario())
    left = [r.getMessage() for r in caplog.records if r.getMessage().startswith("scan cc1 left")]
    said = f"scan cc1 left paused at pose {published}/40 (paused by user)" if paused else \
        f"scan cc1 left at pose {published}/40"
    assert left == [f"{said}, resumable: start the daemon again, then `spadscan ctl resume`"], left
    assert caplog.records[-1].getMessage() == left[0]  # the last word on the scan


async def read_until(arm, pred, timeout_s: float = 20.0) -> None:
    """Read the arm's state until the speed slider it reports satisfies `pred` (the receive stream comes at the
    controller's own pace)."""
    t0 = time.monotonic()
    while True:
        await arm.state()
        if arm.inner.speed_slider is not None and pred(arm.inner.speed_slider):
            return
        assert time.monotonic() - t0 < timeout_s, f"the slider read {arm.inner.speed_slider}"
        await asyncio.sleep(0.01)


def test_a_slowed_speed_slider_shows_in_status_and_once_in_the_log(tmp_path, controller, arun, caplog):  # noqa: F811
    caplog.set_level(logging.INFO, logger="spadscan.daemon")
    cfg = ur_config(tmp_path, controller.host)

    async def scenario():
        arm, sensor = quick_rig(cfg)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                before = runner.status()
                controller.configure(speed_slider=0.05)
                await read_until(arm, lambda slider: slider < 1.0)
                slowed = runner.status()
                controller.configure(speed_slider=1.0)
                await read_until(arm, lambda slider: slider == 1.0)
                return before, slowed, runner.status()
            finally:
                await runner.shutdown()

    before, slowed, after = arun(scenario())
    assert "speed_scaling" not in before and "speed_scaling" not in after, (before, after)
    assert slowed["speed_scaling"] == 0.05, slowed
    assert slowed["speed_note"] == "the controller runs moves at 5 % (the pendant's speed slider)", slowed
    said = [r.getMessage() for r in caplog.records if "speed slider" in r.getMessage()]
    assert said == [f"UR arm {controller.host}: the controller runs moves at 5 % (the pendant's speed slider)",
                    f"UR arm {controller.host}: the controller runs moves at full speed again (the pendant's speed "
                    f"slider at 100 %)"], said
