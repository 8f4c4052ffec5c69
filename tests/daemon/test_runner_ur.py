"""The scan runner driving the UR backend (the real ur_rtde client) against the simulated UR controller on loopback,
with a simulated sensor: the moves arrive at the planned TCP poses, a protective stop pauses the scan, a dropped link
pauses it and `resume` reconnects the arm and completes it, a dead link does not hang the shutdown."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import time

import numpy as np
import pytest

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.arm.ur import URArm
from spadscan.daemon.rig import TrackedArm, build_devices, build_sensor
from spadscan.daemon.config import config_from_dict
from spadscan.daemon.devices import LinkLost
from spadscan.daemon.runner import ScanRunner
from spadscan.daemon.scan_plan import tcp_from_sensor
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import ConfigError, DeviceError

HAND_EYE = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.045], [0, 0, 0, 1]]
_hosts = itertools.count(1)


@pytest.fixture
def controller():
    from spadscan.daemon.ursim.remote import SimURProcess

    for _ in range(10):
        try:
            sim = SimURProcess(f"127.78.{os.getpid() % 250}.{next(_hosts) % 240 + 1}", time_scale=0.05)
            break
        except DeviceError:  # address in use
            continue
    else:
        raise AssertionError("no free loopback address for the simulated controller")
    yield sim
    sim.close()


async def until(pred, what: str, timeout_s: float = 60.0) -> None:
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout_s, f"timed out waiting for {what}"
        await asyncio.sleep(0.01)


def ur_config(tmp_path, host: str, watchdog_hz: float = 1.0):
    return config_from_dict({
        # No `socket`: the default, in the test's short private folder (conftest); one under tmp_path is too long
        # where TMPDIR is.
        "captures": str(tmp_path / "caps"),
        "arm": {"backend": "ur", "host": host, "speed": 0.5, "acceleration": 2.0, "hand_eye": HAND_EYE,
                "workspace_min": [0.0, -0.5, 0.02], "workspace_max": [0.9, 0.5, 0.7], "min_reach_m": 0.1,
                "max_reach_m": 0.85, "move_timeout_s": 30.0, "watchdog_hz": watchdog_hz},
        "sensor": {"backend": "sim", "mesh": "builtin:pyramid", "mesh_offset_m": [0.4, 0, 0], "rays_per_zone": 8},
        "scan": {"views": 8, "frames_per_pose": 1, "settle_s": 0.0, "radius_m": 0.25, "target": [0.4, 0, 0.05],
                 "min_elevation_deg": 30, "max_elevation_deg": 80}}, tmp_path / "rig.toml")


def quick_rig(cfg):
    """The config's rig, with a UR arm that gives up on a silent link after 5 s instead of 10 s."""
    arm = TrackedArm(URArm(cfg.arm.device.host, speed=cfg.arm.speed, accel=cfg.arm.acceleration, timeout_s=5.0,
                           stale_after_s=1.0, watchdog_hz=cfg.arm.device.watchdog_hz))
    return arm, build_sensor(cfg, arm)


@contextlib.asynccontextmanager
async def ur_runner(cfg):
    """(arm, runner) of the config's rig (`quick_rig`), its devices up; the runner shut down and the devices released
    on the way out."""
    arm, sensor = quick_rig(cfg)
    async with DeviceSession([arm, sensor]):
        runner = ScanRunner(arm, sensor, cfg)
        try:
            yield arm, runner
        finally:
            await runner.shutdown()


def check_every_pose_once(path, hand_eye=HAND_EYE) -> None:
    reader = CaptureReader(path)
    data = reader.load()
    assert reader.state == "complete"
    assert sorted(data.pose_indices.tolist()) == list(range(8))
    planned_tcp = tcp_from_sensor(reader.planned_poses(), np.array(hand_eye))
    for m in data.meta:  # every pose was reached: the simulated controller is exact
        np.testing.assert_allclose(np.array(m["tcp_pose"]), planned_tcp[m["pose_index"]], atol=1e-5)


@pytest.mark.slow
def test_scan_on_the_ur_controller_with_a_protective_stop(tmp_path, controller, arun):
    """The controller pauses its program on the protective stop, as a real one does: after the operator clears the
    stop, `resume` finds the control script not running, uploads it again and the scan completes."""
    # The config's slowest watchdog (2 s of silence): this test is about the protective stop, and on a busy machine
    # a 1 s watchdog may stop the script first (its own tests are in test_arm_ur).
    cfg = ur_config(tmp_path, controller.host, watchdog_hz=0.5)

    async def scenario():
        arm, sensor = build_devices(cfg)
        assert isinstance(arm, TrackedArm)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                await runner.start("ur")
                await until(lambda: runner.job.next_pose >= 2, "two poses")
                await asyncio.to_thread(controller.protective_stop)
                await until(lambda: runner.state == "paused", "the pause")
                reason = runner.status()["reason"]
                assert "protective stop" in reason, f"paused for another reason: {reason}; controller: " \
                    f"{(await asyncio.to_thread(controller.state))['errors']}"
                await asyncio.to_thread(controller.clear_protective_stop)
                scripts = await asyncio.to_thread(controller.scripts)
                await runner.resume()
                done = await runner.wait("ur")
            finally:
                await runner.shutdown()
        return reason, done, await asyncio.to_thread(lambda: controller.moves), scripts, controller.scripts()

    reason, done, moves, scripts, scripts_after = arun(scenario(), timeout_s=180)
    assert "protective stop" in reason and done["state"] == "complete"
    assert scripts_after == scripts + 1  # uploaded again on resume
    reader = CaptureReader(tmp_path / "caps" / "ur")
    data = reader.load()
    assert sorted(data.pose_indices.tolist()) == list(range(8))
    planned_tcp = tcp_from_sensor(reader.planned_poses(), np.array(HAND_EYE))
    # Every pose was reached: the actual TCP pose recorded is the planned one (the simulated controller is exact).
    for m in data.meta:
        np.testing.assert_allclose(np.array(m["tcp_pose"]), planned_tcp[m["pose_index"]], atol=1e-5)
    # Every moveL the controller took went to a planned TCP pose (one may have been cut short by the stop and sent
    # again after resume).
    targets = [np.array(mv.target[:3]) for mv in moves if mv.name == "moveL"]
    assert len(targets) >= 8
    for t in targets:
        assert np.min(np.linalg.norm(planned_tcp[:, :3, 3] - t, axis=1)) < 1e-6


def test_a_pose_the_controller_refuses_stops_the_scan_before_anything_moves(tmp_path, controller, arun):
    """The controller's safety planes are stricter than the config's box: asked about every planned pose before the
    first move, it refuses one, and the scan is refused in one line naming it; nothing moves, no folder is made."""
    cfg = ur_config(tmp_path, controller.host)
    controller.configure(safety_floor_z=0.25)

    async def scenario():
        arm, sensor = build_devices(cfg)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                with pytest.raises(ConfigError) as refused:
                    await runner.start("ur")
                return str(refused.value), runner.status()["state"]
            finally:
                await runner.shutdown()

    message, state = arun(scenario(), timeout_s=120)
    assert message.startswith("scan 'ur': UR arm") and "is outside the controller's safety limits" in message
    assert state == "idle" and not (tmp_path / "caps" / "ur").exists()
    assert [m.name for m in controller.moves] == ["stopL"]  # the release on the way out; no move
    queries = controller.state()["queries"]
    assert queries[-1][0] == "within_safety_limits" and not queries[-1][2] and queries[-1][1][2] < 0.25


def test_a_tcp_offset_left_on_the_pendant_keeps_the_daemon_from_starting(tmp_path, controller, arun):
    """The pendant's active TCP is a 120 mm pointer, not the bare flange the config's hand_eye is measured from: the
    rig does not start, in one line naming the offset and what to do; nothing moves, no scan can begin."""
    cfg = ur_config(tmp_path, controller.host)
    controller.configure(tcp_offset=[0.0, 0.0, 0.12, 0.0, 0.0, 0.0])

    async def scenario():
        arm, sensor = build_devices(cfg)
        with pytest.raises(DeviceError) as refused:
            async with DeviceSession([arm, sensor]):
                pass
        return str(refused.value)

    message = arun(scenario(), timeout_s=120)
    assert "\n" not in message and message.startswith("rig did not start: UR arm"), message
    assert "active TCP offset is [0.0, 0.0, 120.0] mm, [0.00, 0.00, 0.00] deg" in message, message
    assert "bare-flange TCP" in message
    assert [m.name for m in controller.moves] == ["stopL"]  # the release on the way out; no move
    assert not (tmp_path / "caps" / "ur").exists()


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["close", "silent"])
def test_resume_after_a_dropped_link_reconnects_and_completes(tmp_path, controller, arun, mode):
    """"close": the controller closes every connection; "silent": a pulled cable, where ur_rtde's moveL blocks for
    good. Either way the scan pauses (the ur_rtde process is ended), and once the link is back `resume` reconnects (a
    fresh process with fresh interfaces) and completes the scan; the shutdown is clean."""
    cfg = ur_config(tmp_path, controller.host)

    async def scenario():
        async with ur_runner(cfg) as (_, runner):
            await runner.start("ur")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            await asyncio.to_thread(controller.drop_link, mode)
            await until(lambda: runner.state == "paused", "the pause")
            reason = runner.status()["reason"]
            sessions = (await asyncio.to_thread(controller.connections))["rtde"]
            await asyncio.to_thread(controller.restore_link)
            await runner.resume()
            await until(lambda: runner.state != "scanning", "the resumed scan to end or pause")
            status = runner.status()
        return reason, status, (await asyncio.to_thread(controller.connections))["rtde"] - sessions

    reason, status, new_sessions = arun(scenario(), timeout_s=180)
    assert "link lost" in reason
    assert status["state"] == "idle" and status["last_scan"] == {"name": "ur", "state": "complete"}, status
    assert new_sessions == 2  # resuming built a new receive and a new control interface
    check_every_pose_once(tmp_path / "caps" / "ur")


async def bounce_link(controller, arm) -> None:
    """The controller closes every connection (a reboot, a re-plugged cable) and, once the arm has found its link
    down, comes back."""
    await asyncio.to_thread(controller.drop_link, "close")
    async with asyncio.timeout(60):
        while True:
            try:
                await arm.state()
            except LinkLost:
                break
            await asyncio.sleep(0.05)
    await asyncio.to_thread(controller.restore_link)


@pytest.mark.slow
def test_a_scan_started_after_the_link_dropped_while_idle_reconnects_and_completes(tmp_path, controller, arun):
    """The controller closes every connection while no scan runs (a reboot, a re-plugged cable) and comes back: the
    next `scan` reconnects (as `resume` does) instead of being refused until the daemon restarts."""
    cfg = ur_config(tmp_path, controller.host)

    async def scenario():
        async with ur_runner(cfg) as (arm, runner):
            sessions = (await asyncio.to_thread(controller.connections))["rtde"]
            await bounce_link(controller, arm)
            await runner.start("ur")
            await until(lambda: runner.state != "scanning", "the scan to end or pause")
            status = runner.status()
        return status, (await asyncio.to_thread(controller.connections))["rtde"] - sessions

    status, new_sessions = arun(scenario(), timeout_s=180)
    assert status["state"] == "idle" and status["last_scan"] == {"name": "ur", "state": "complete"}, status
    assert new_sessions == 2  # a new receive and a new control interface
    check_every_pose_once(tmp_path / "caps" / "ur")


@pytest.mark.slow
def test_a_link_that_dropped_and_came_back_while_paused_is_reconnected_by_the_first_resume(tmp_path, controller,
                                                                                           arun):
    """The scan is paused by the operator; meanwhile the controller closes every connection (a reboot, a re-plugged
    cable) and comes back. The first `resume` reconnects (as after a lost link) and completes the scan, instead of
    pausing again with "link lost" and needing a second resume."""
    cfg = ur_config(tmp_path, controller.host)

    async def scenario():
        async with ur_runner(cfg) as (arm, runner):
            await runner.start("ur")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            await runner.pause()
            await until(lambda: runner.state == "paused", "the pause")
            sessions = (await asyncio.to_thread(controller.connections))["rtde"]
            await bounce_link(controller, arm)
            await runner.resume()
            await until(lambda: runner.state != "scanning", "the resumed scan to end or pause")
            status = runner.status()
            # (here: a link left down would also fail the release on the way out, hiding why)
            assert status["state"] == "idle" and status["last_scan"] == {"name": "ur", "state": "complete"}, status
        return (await asyncio.to_thread(controller.connections))["rtde"] - sessions

    new_sessions = arun(scenario(), timeout_s=180)
    assert new_sessions == 2  # the first resume built a new receive and a new control interface
    check_every_pose_once(tmp_path / "caps" / "ur")


@pytest.mark.slow
def test_an_arm_restarted_powered_off_pauses_each_resume_until_it_runs_then_the_scan_completes(tmp_path, controller,
                                                                                               arun):
    """A safety fault pauses the scan; the operator restarts the arm, which comes back powered off, and the
    controller's connections drop meanwhile (a reboot). A resume reconnects, and the arm refuses the script: the scan
    pauses again, saying to power the arm on and release its brakes; once that is done, the next resume reconnects
    again (not only the fault's clearing, over a link that is down) and completes the scan."""
    cfg = ur_config(tmp_path, controller.host)

    async def scenario():
        async with ur_runner(cfg) as (arm, runner):
            await runner.start("ur")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            await asyncio.to_thread(controller.safety_fault, "fault")
            await until(lambda: runner.state == "paused", "the pause")
            reasons = [runner.status()["reason"]]
            await asyncio.to_thread(controller.restart_safety)
            await bounce_link(controller, arm)
            await runner.resume()
            await until(lambda: runner.state != "scanning", "the resumed scan to pause")
            reasons.append(runner.status()["reason"])
            await asyncio.to_thread(controller.power_on)
            await asyncio.to_thread(controller.release_brakes)
            await runner.resume()
            await until(lambda: runner.state != "scanning", "the resumed scan to end or pause")
            return reasons, runner.status()

    reasons, status = arun(scenario(), timeout_s=240)
    assert "safety fault" in reasons[0], reasons
    assert "the arm is powered off (robot mode 3): power it on and release the brakes" in reasons[1], reasons
    assert status["state"] == "idle" and status["last_scan"] == {"name": "ur", "state": "complete"}, status
    check_every_pose_once(tmp_path / "caps" / "ur")


@pytest.mark.slow
def test_shutdown_on_a_dead_link_does_not_hang(tmp_path, controller, arun):
    """The link stays down (silent: ur_rtde's moveL blocks for good): shutting down reports the dead link at once
    instead of waiting on ur_rtde, and leaves the scan resumable."""
    cfg = ur_config(tmp_path, controller.host)

    async def scenario():
        arm, sensor = quick_rig(cfg)
        session = DeviceSession([arm, sensor])
        await session.__aenter__()
        runner = ScanRunner(arm, sensor, cfg)
        try:
            await runner.start("ur")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            await asyncio.to_thread(controller.drop_link, "silent")
            await until(lambda: runner.state == "paused", "the pause")
            reason = runner.status()["reason"]
        finally:
            await runner.shutdown()
        with pytest.raises(DeviceError) as down:
            await session.__aexit__(None, None, None)
        return reason, str(down.value)

    reason, down = arun(scenario(), timeout_s=120)
    assert "link lost" in reason
    # Only release fails, at once, with the reason the link was ended: moveL got no answer (in the arm's time, or the
    # runner gave up first and the next call found it overdue), or (when moveL returned before the link dropped) the
    # receive data went stale, or ur_rtde itself gave the silent connection up first (the watchdog's kicks go out on
    # it); close does not wait on ur_rtde.
    assert (("moveL" in down and "no answer" in down) or "receive data stale" in down
            or "link closed (ur_rtde reports disconnected)" in down), down
    assert "reconnect first" in down, down
    assert "did not finish" not in down and "still busy" not in down, down
    assert CaptureReader(tmp_path / "caps" / "ur").state == "running"
