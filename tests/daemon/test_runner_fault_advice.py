"""Every pause reason says, on one line, what happened and what the operator does before `spadscan ctl resume`: a
full disk, a sensor whose link is down (it reconnects by itself, the scan does not go on by itself; once the link
is back the reason says so), a sensor silent with its link up, the arm's controller out of reach (also when a scan
is started); and a safety stop that came as the move ended, before the frames, is not said to have come while the
pose was captured."""

from __future__ import annotations

import errno
import re

import numpy as np
import pytest

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.arm.sim import SimArmFaults
from spadscan.daemon.arm.stops import PROTECTIVE_STOP, TO_CLEAR
from spadscan.daemon.devices import LinkLost
from spadscan.daemon.runner import ScanRunner
from spadscan.daemon.sensor.serial_bridge import SerialSensor
from spadscan.daemon.sensor.sim_bridge import SimBridge

from test_abort_durable import disk  # noqa: F401  (a fixture)
from test_runner import (TimedArm, check_capture, daemon_runner, make_cfg, make_rig, paused_after,  # noqa: F401
                         sphere, until)

WAIT = "`spadscan ctl resume` once the sensor's link is back (the scan does not go on by itself)"
BACK = "the sensor's link is back now: `spadscan ctl resume`"
ARM_LINK = ("check the network to the arm's controller and that the controller is on, then `spadscan ctl resume` "
            "(it reconnects)")


def test_a_full_disk_says_to_make_room(arun, tmp_path, sphere, disk):  # noqa: F811
    cfg = make_cfg(tmp_path, views=6)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            return await paused_after(runner, "full", lambda: disk.update(error=errno.ENOSPC))

    status = arun(scenario())
    assert re.fullmatch(r"disk full while publishing: No space left on device \([^()]+\); make room on the "
                        r"captures' disk, then `spadscan ctl resume` \(pose \d/6\)", status["reason"]), status


def test_a_lost_sensor_link_says_to_resume_once_it_is_back_and_then_that_it_is(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=6, frame_timeout_s=0.5)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            down = await paused_after(runner, "unplug", lambda: runner.sensor.inject_link_loss(3600.0))
            runner.sensor.end_link_loss()  # plugged in again
            back = runner.status()
            await runner.resume()
            return down, back, await runner.wait("unplug")

    down, back, done = arun(scenario())
    assert re.fullmatch(rf"link lost: sensor sim: link down for another [\d.]+ s \(injected\); {re.escape(WAIT)} "
                        rf"\(pose \d/6\)", down["reason"]), down["reason"]
    assert ARM_LINK not in down["reason"]  # the sensor's link, not the arm's
    assert back["reason"] == down["reason"].replace(WAIT, BACK), back["reason"]
    assert back["last_error"] == back["reason"]
    assert done == {"name": "unplug", "state": "complete"}


@pytest.mark.usefixtures("no_leaked_threads_or_fds")
def test_an_unplugged_serial_sensor_says_to_resume_once_its_link_is_back(arun, tmp_path, sphere):  # noqa: F811
    """The serial sensor on the bridge twin, unplugged mid-scan: its frame timeout comes before its link's grace
    (a silent sensor whose link is down), and the reason names the link and what to do; replugged, the reason says
    the link is back, and the resume completes the scan."""
    cfg = make_cfg(tmp_path, views=6, frame_timeout_s=1.0)
    rng = np.random.default_rng(5)

    async def scenario(bridge):
        arm = TimedArm(motion_time_s=0.01)
        sensor = SerialSensor(bridge.port, period_ms=50, link_grace_s=30.0)
        async with DeviceSession([arm, sensor]):
            bridge.start_measuring(lambda: rng.integers(0, 1 << 16, (10, 128)), 0.05)
            runner = ScanRunner(arm, sensor, cfg)
            try:
                down = await paused_after(runner, "serial", bridge.unplug)
                bridge.replug()
                await until(lambda: sensor.counters()["link"] == "up", "the link back")
                back = runner.status()
                await runner.resume()
                done = await runner.wait("serial")
            finally:
                await runner.shutdown()
                bridge.stop_stream()
        return down, back, done

    with SimBridge() as bridge:
        down, back, done = arun(scenario(bridge))
    assert down["reason"].startswith("sensor silent: sensor serial "), down["reason"]
    assert "no complete frame within 1 s (frame_timeout_s) at pose " in down["reason"], down["reason"]
    assert "; the link has been down for " in down["reason"] and down["reason"].endswith(f"; {WAIT} (pose "
                                                                                         f"{down['pose']}/6)")
    assert back["reason"] == down["reason"].replace(WAIT, BACK), back["reason"]
    assert done == {"name": "serial", "state": "complete"}
    check_capture(tmp_path / "caps" / "serial", 6, 2)


def test_a_silent_sensor_with_its_link_up_says_what_to_check(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=6, frame_timeout_s=0.5)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            return await paused_after(runner, "quiet", lambda: runner.sensor.inject_silence(3600.0))

    reason = arun(scenario())["reason"]
    assert re.fullmatch(r"sensor silent: sensor sim: no complete frame within 0\.5 s \(frame_timeout_s\) at pose "
                        r"\d; check the sensor, its cable, its power and its bridge \(or raise \[sensor\] "
                        r"frame_timeout_s\), then `spadscan ctl resume` \(pose \d/6\)", reason), reason


def test_the_arms_lost_link_says_to_check_the_network_and_the_controller(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=6)

    async def scenario():
        async with daemon_runner(cfg, sphere, faults=SimArmFaults(link_drop_on_moves=(3,))) as runner:
            await runner.start("net")
            await until(lambda: runner.state == "paused", "the pause")
            return runner.status()

    reason = arun(scenario())["reason"]
    assert re.fullmatch(rf"link lost: arm \(sim\): link lost \(no fresh state data\); {re.escape(ARM_LINK)} "
                        rf"\(pose 2/6\)", reason), reason


def test_a_scan_started_while_the_arms_link_is_down_says_what_to_check(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=4)

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            runner.arm.drop_link()  # a cable pulled while no scan runs; the start's reconnect fails too
            with pytest.raises(LinkLost) as refused:
                await runner.start("down")
            runner.arm.restore_link()
            await runner.start("down")
            return str(refused.value), await runner.wait("down")

    refused, done = arun(scenario())
    assert refused == ("cannot start scan 'down': arm (sim): link lost (no fresh state data); check the network "
                       "to the arm's controller and that the controller is on, then start the scan again"), refused
    assert done == {"name": "down", "state": "complete"}


def test_a_safety_stop_as_the_arm_arrives_is_not_said_to_come_while_capturing(arun, tmp_path, sphere):  # noqa: F811
    """The protective stop comes as the move to pose 2 ends (the arm settling, before any frame of it): the reason
    says so, not 'while capturing pose 2'; the resume takes pose 2 and completes the scan."""
    cfg = make_cfg(tmp_path, views=6, settle_s=0.05)

    async def scenario():
        arm, sensor = make_rig(cfg, sphere, motion_time_s=0.01)
        move, fired = arm.move_to, []

        async def move_to(tcp_pose, speed, accel):
            await move(tcp_pose, speed, accel)
            if arm.moves == 3 and not fired:  # arrived at pose 2
                fired.append(True)
                arm.trigger_stop(PROTECTIVE_STOP)

        arm.move_to = move_to
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                await runner.start("arrive")
                await until(lambda: runner.state == "paused", "the pause")
                reason = runner.status()["reason"]
                await runner.resume()
                return reason, await runner.wait("arrive")
            finally:
                await runner.shutdown()

    reason, done = arun(scenario())
    assert reason == (f"arm fault: protective stop on arm (sim) at pose 2, as the move there ended or the arm "
                      f"settled (before its frames); {TO_CLEAR[PROTECTIVE_STOP]}, then resume (pose 2/6)"), reason
    assert done == {"name": "arrive", "state": "complete"}
    check_capture(tmp_path / "caps" / "arrive", 6, 2)

