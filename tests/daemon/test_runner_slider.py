"""A move the pendant's speed slider slows is not taken for a stuck one: the runner's move_timeout_s counts motion
time, at the slider's pace; a move that times out all the same says what the slider was at; and the reply to a
resume, and `ctl status` while the scan is paused, show the slider as it is then, not as it was read before the
pause (a reading that cannot be renewed is shown with its age)."""

from __future__ import annotations

import asyncio
import re
import time
from dataclasses import replace

import pytest

from spadscan.daemon.app import DeviceSession, Dispatcher
from spadscan.daemon.arm.sim import SimArmFaults
from spadscan.daemon.devices import LinkLost
from spadscan.daemon.backends import pose_provider
from spadscan.daemon.runner import ScanRunner
from spadscan.daemon.speed_slider import SLIDER_OLD_S
from spadscan.daemon.sensor.sim import SimSensor
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings

from test_runner import TimedArm, check_capture, make_cfg, sphere, until  # noqa: F401  (sphere: a fixture)
from test_runner_ur import controller, quick_rig, ur_config  # noqa: F401  (controller: a fixture)


class SliderArm(TimedArm):
    """A sim arm with a speed slider, as a UR controller has: `slider` is the pendant's (a move takes its motion
    time divided by it), `speed_slider` the daemon's reading of it and `speed_slider_at` when it was taken, whenever
    the arm is read (a move, a state, `read_speed_slider`), as `URArm` takes it. `slider_link` False: the slider
    cannot be read (the link is down)."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.slider = 1.0
        self.speed_slider: float | None = None
        self.speed_slider_at: float | None = None
        self.slider_link = True

    def motion_time(self, start, goal, speed, accel):
        return super().motion_time(start, goal, speed, accel) / self.slider

    def _note(self) -> None:
        self.speed_slider, self.speed_slider_at = self.slider, time.monotonic()

    async def move_to(self, tcp_pose, speed, accel):
        self._note()
        await super().move_to(tcp_pose, speed, accel)

    async def state(self):
        self._note()
        return await super().state()

    async def read_speed_slider(self):
        if not self.slider_link:
            raise LinkLost("arm (sim): link down")
        self._note()


async def slider_scan(cfg, mesh, name: str, arm: SliderArm, then=None):
    """Run scan `name` with `arm` until it ends or pauses; `then(runner)` after that, if given. Returns the status
    at the end or pause, and what `then` returned."""
    sensor = SimSensor(sensor_preset("tmf8820"), mesh, pose_provider(arm, cfg.arm.hand_eye),
                       settings=SimSettings(rays_per_zone=16), seed=1, frame_time_s=0.0)
    async with DeviceSession([arm, sensor]):
        runner = ScanRunner(arm, sensor, cfg)
        try:
            await runner.start(name)
            await until(lambda: runner.state in ("idle", "paused"), "the scan to end or pause", 60.0)
            status = runner.status()
            return status, (await then(runner) if then is not None else None)
        finally:
            await runner.shutdown()


def test_a_move_the_speed_slider_slows_is_not_taken_for_a_stuck_one(arun, tmp_path, sphere):  # noqa: F811
    """The slider at 10 %: every move takes 1 s, twice move_timeout_s, but only 0.1 s of motion: the scan
    completes, no move is stopped as stuck."""
    cfg = make_cfg(tmp_path, views=3, arm={"move_timeout_s": 0.5})
    arm = SliderArm(motion_time_s=0.1)
    arm.slider = 0.1
    status, _ = arun(slider_scan(cfg, sphere, "slow", arm))
    assert status["state"] == "idle" and status["last_scan"] == {"name": "slow", "state": "complete"}, status
    assert arm.moves == 3
    check_capture(tmp_path / "caps" / "slow", 3, 2)


def test_a_move_that_times_out_with_the_slider_down_names_the_slider(arun, tmp_path, sphere):  # noqa: F811
    """A move that does not end (30 s of motion) with the slider at 50 %: stopped after 0.2 s of motion, 0.4 s of
    wall time at the least, and the reason says the limit was counted at the slider's pace, and what it was."""
    cfg = make_cfg(tmp_path, views=3, arm={"move_timeout_s": 0.2})
    arm = SliderArm(motion_time_s=30.0)
    arm.slider = 0.5
    status, _ = arun(slider_scan(cfg, sphere, "stuck", arm))
    reason = status["reason"]
    assert status["state"] == "paused", status
    said = re.fullmatch(r"arm fault: arm \(sim\): move to pose 0 did not finish within 0\.2 s \(move_timeout_s\) "
                        r"of motion, counted at the pace of the pendant's speed slider \(at 50 %; ([\d.]+) s in "
                        r"all\); see on the teach pendant what holds the arm up, then `spadscan ctl resume` "
                        r"\(pose 0/3\)", reason)
    assert said is not None, reason
    assert float(said.group(1)) >= 0.39, reason


def test_the_reply_to_a_resume_shows_the_speed_slider_as_it_is_then(arun, tmp_path, sphere):  # noqa: F811
    """The slider at 5 % when a protective stop pauses the scan; the operator sets it back to 100 % before
    resuming: the resume's reply says nothing of a slowed arm (a paused arm is not read: the reading from before
    the pause must not stand for the slider now)."""
    cfg = make_cfg(tmp_path, views=4)
    arm = SliderArm(motion_time_s=0.0005, faults=SimArmFaults(protective_stop_on_moves=(2,)))
    arm.slider = 0.05

    async def resumed(runner):
        arm.slider = 1.0  # the pendant's slider back at 100 %, while the scan is paused
        reply = await runner.resume()
        return reply, await runner.wait("fresh")

    paused, (reply, done) = arun(slider_scan(cfg, sphere, "fresh", arm, resumed))
    assert paused["state"] == "paused" and paused["speed_scaling"] == 0.05, paused
    assert reply["state"] == "scanning", reply
    assert "speed_scaling" not in reply and "speed_note" not in reply, reply
    assert done == {"name": "fresh", "state": "complete"}


def paused_with_the_slider_down(arun, cfg, mesh, meanwhile):
    """Scan 'held' paused by a protective stop with the slider at 5 %; then `meanwhile(arm)` (what changes while it
    is paused) and `ctl status` (through the daemon's dispatcher). Returns that status."""
    arm = SliderArm(motion_time_s=0.0005, faults=SimArmFaults(protective_stop_on_moves=(2,)))
    arm.slider = 0.05

    async def asked(runner):
        meanwhile(arm)
        return await Dispatcher(runner, asyncio.Event(), cfg)({"op": "status"})

    paused, status = arun(slider_scan(cfg, mesh, "held", arm, asked))
    assert paused["state"] == "paused" and paused["speed_scaling"] == 0.05, paused
    return status


@pytest.mark.parametrize("now", [1.0, 0.2])
def test_status_while_paused_reads_the_slider_afresh(arun, tmp_path, sphere, now):  # noqa: F811
    """The slider set back to 100 % while the scan is paused (no move reads it): `ctl status` says nothing of a
    slowed arm; one set to 20 % meanwhile is shown at 20 %, read just now."""
    cfg = make_cfg(tmp_path, views=4)
    status = paused_with_the_slider_down(arun, cfg, sphere, lambda arm: setattr(arm, "slider", now))
    assert status["state"] == "paused", status
    if now == 1.0:
        assert "speed_scaling" not in status and "speed_note" not in status, status
    else:
        assert status["speed_scaling"] == 0.2 and status["speed_scaling_age_s"] < SLIDER_OLD_S, status
        assert status["speed_note"] == "the controller runs moves at 20 % (the pendant's speed slider)", status


def test_a_slider_that_cannot_be_read_afresh_is_shown_with_its_age(arun, tmp_path, sphere):  # noqa: F811
    """The arm's link is down while paused: status shows the slider as last read, and how long ago."""
    cfg = make_cfg(tmp_path, views=4)

    def link_down(arm):
        arm.slider_link, arm.slider = False, 1.0
        arm.speed_slider_at = time.monotonic() - 60.0  # read a minute ago, before the pause

    status = paused_with_the_slider_down(arun, cfg, sphere, link_down)
    assert status["speed_scaling"] == 0.05 and 60.0 <= status["speed_scaling_age_s"] < 90.0, status
    assert re.fullmatch(r"the controller runs moves at 5 % \(the pendant's speed slider, as read (6\d|[78]\d) s "
                        r"ago\)", status["speed_note"]), status["speed_note"]


@pytest.mark.slow
def test_the_slider_lowered_on_the_ur_controller_mid_scan_slows_the_scan_without_pausing_it(tmp_path, controller,
                                                                                             arun):  # noqa: F811
    """The real ur_rtde client and the simulated controller: the slider lowered to 5 % once the first pose is in
    makes every move 20 times as long (about 4 s, move_timeout_s 1.5 s): the scan goes on. Paused by the operator,
    the slider set back to 100 %: the resume's reply says nothing of a slowed arm."""
    base = ur_config(tmp_path, controller.host)
    cfg = replace(base, arm=replace(base.arm, speed=0.05, move_timeout_s=1.5), scan=replace(base.scan, views=5))

    async def scenario():
        arm, sensor = quick_rig(cfg)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                await runner.start("ursl")
                await until(lambda: runner.job.next_pose >= 1, "the first pose")
                await asyncio.to_thread(controller.configure, speed_slider=0.05)
                await until(lambda: runner.state == "paused" or runner.job.next_pose >= 3, "two slowed poses")
                slowed = runner.status()
                await runner.pause()
                await until(lambda: runner.state in ("paused", "idle"), "the pause")
                await asyncio.to_thread(controller.configure, speed_slider=1.0)
                reply = await runner.resume() if runner.state == "paused" else None
                return slowed, reply, await runner.wait("ursl")
            finally:
                await runner.shutdown()

    slowed, reply, done = arun(scenario(), timeout_s=180.0)
    assert slowed["state"] != "paused" and slowed["reason"] is None, slowed
    assert slowed["speed_scaling"] == 0.05, slowed
    assert reply is None or ("speed_scaling" not in reply and "speed_note" not in reply), reply
    assert done == {"name": "ursl", "state": "complete"}
