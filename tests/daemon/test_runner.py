"""The scan runner with the simulated arm and the simulated sensor: every pose exactly once, actual poses, faults
that pause with their reason, resume at the first unpublished pose, nothing published ever lost."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import inspect
import logging
import re
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.arm.sim import SimArm, SimArmFaults, fake_joints
from spadscan.daemon.arm.stops import EMERGENCY_STOP, PROTECTIVE_STOP, SAFEGUARD_STOP, TO_CLEAR
from spadscan.daemon.backends import pose_provider
from spadscan.daemon.config import config_from_dict
from spadscan.daemon.devices import SensorSilent
from spadscan.daemon.runner import ScanRunner
from spadscan.daemon.sensor.sim import SimSensor
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.errors import CaptureError, ConfigError
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings

from disk_faults import switchable_full_disk

HAND_EYE = [[0.0, -1, 0, 0.0], [1, 0, 0, 0.0], [0, 0, 1, 0.05], [0, 0, 0, 1]]


@pytest.fixture(scope="module")
def sphere():
    from spadscan.protocol.scenes import builtin_scene

    return builtin_scene("sphere")


def make_cfg(tmp_path: Path, *, auto_resume: bool = False, frame_timeout_s: float = 5.0, arm: dict | None = None,
             **scan):
    scan = {"views": 10, "frames_per_pose": 2, "settle_s": 0.0, "radius_m": 0.4, "target": [0, 0, 0.1], **scan}
    return config_from_dict({
        # No `socket`: the default, in the test's short private folder (conftest); one under tmp_path is too long
        # where TMPDIR is.
        "captures": str(tmp_path / "caps"), "auto_resume": auto_resume,
        "arm": {"backend": "sim", "hand_eye": HAND_EYE, **(arm or {})},
        "sensor": {"backend": "sim", "mesh": "builtin:sphere", "rays_per_zone": 16,
                   "frame_timeout_s": frame_timeout_s},
        "scan": scan}, tmp_path / "rig.toml")


class TimedArm(SimArm):
    """Remembers when each move ended."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.stops: list[float] = []

    async def move_to(self, tcp_pose, speed, accel):
        await super().move_to(tcp_pose, speed, accel)
        self.stops.append(time.monotonic())


def make_rig(cfg, mesh, *, frame_time_s=0.0, **arm_kw):
    arm = TimedArm(**{"motion_time_s": 0.0, **arm_kw})
    sensor = SimSensor(sensor_preset("tmf8820"), mesh, pose_provider(arm, cfg.arm.hand_eye),
                       settings=SimSettings(rays_per_zone=16), seed=1, frame_time_s=frame_time_s)
    return arm, sensor


@contextlib.asynccontextmanager
async def daemon_runner(cfg, mesh, **rig_kw):
    """A ScanRunner on make_rig's sim devices, its devices connected; shut down however the test ends."""
    arm, sensor = make_rig(cfg, mesh, **rig_kw)
    async with DeviceSession([arm, sensor]):
        runner = ScanRunner(arm, sensor, cfg)
        try:
            yield runner
        finally:
            await runner.shutdown()


async def until(pred, what: str, timeout_s: float = 20.0) -> None:
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.005)


async def paused_after(runner: ScanRunner, name: str, fault, what: str = "the pause", poses: int = 2) -> dict:
    """The scenario most runner tests begin with: start scan `name`, let `poses` poses in, then `fault()` (a fault
    injected, a disk filled, or the operator's `runner.pause`: awaited when it returns an awaitable), and wait for the
    pause it makes (`what`: said if it never comes). Returns the status then."""
    await runner.start(name)
    await until(lambda: runner.job.next_pose >= poses, f"{poses} poses")
    done = fault()
    if inspect.isawaitable(done):
        await done
    await until(lambda: runner.state == "paused", what)
    return runner.status()


async def resumed_after_pause(runner: ScanRunner, name: str, meanwhile=lambda: None) -> tuple[str, dict]:
    """Once scan `name` has paused: its reason; then `meanwhile()` (the fault fixed), resume, and the scan's end."""
    await until(lambda: runner.state == "paused", "the pause")
    reason = runner.status()["reason"]
    meanwhile()
    await runner.resume()
    return reason, await runner.wait(name)


def check_capture(path: Path, n: int, k: int, state: str = "complete"):
    """Every pose 0..n-1 exactly once with frames 0..k-1; sensor pose = recorded actual TCP @ hand-eye."""
    r = CaptureReader(path)
    data = r.load()
    assert r.state == state
    got = sorted(zip(data.pose_indices.tolist(), [m["frame"] for m in data.meta]))
    assert got == [(i, f) for i in range(n) for f in range(k)]
    tcp = np.array([m["tcp_pose"] for m in data.meta])
    np.testing.assert_allclose(data.poses, tcp @ np.array(HAND_EYE), atol=1e-12)
    return data


def test_scan_stores_each_frame_at_the_actual_pose(arun, tmp_path, sphere):
    cfg = make_cfg(tmp_path, views=8, frames_per_pose=3)

    async def scenario():
        async with daemon_runner(cfg, sphere, pose_noise_m=0.002) as runner:
            arm = runner.arm
            started = await runner.start("ball")
            done = await runner.wait("ball")
            return started, done, runner.status(), [c.copy() for c in arm.commanded]

    started, done, status, commanded = arun(scenario())
    assert started["state"] == "scanning" and started["poses"] == 8
    assert done == {"name": "ball", "state": "complete"}
    assert status["state"] == "idle" and status["last_scan"] == {"name": "ball", "state": "complete"}
    data = check_capture(tmp_path / "caps" / "ball", 8, 3)
    assert data.hists.shape == (24, 9, 128) and data.hists.dtype == np.uint32
    assert data.reference is not None  # the TMF8820 model carries reference histograms
    planned = CaptureReader(tmp_path / "caps" / "ball").planned_poses()
    for m, pose in zip(data.meta, data.poses):
        i = m["pose_index"]
        # The actual pose: what the sensor saw (render pose), not the commanded one (1-2 mm away with noise).
        np.testing.assert_allclose(pose, np.array(m["extra"]["render_pose"]), atol=1e-12)
        off = np.linalg.norm(np.array(m["tcp_pose"])[:3, 3] - commanded[i][:3, 3])
        assert 0 < off < 0.02
        assert np.linalg.norm(pose[:3, 3] - planned[i][:3, 3]) < 0.02
        np.testing.assert_allclose(m["joints"], fake_joints(np.array(m["tcp_pose"])))
        assert m["t_start"] <= m["t_end"]
    # Frames are separate measurements, never summed: K distinct exposures per pose.
    starts = {(m["pose_index"], m["t_start"]) for m in data.meta}
    assert len(starts) == 24


def test_frames_that_began_before_the_arm_settled_are_dropped(arun, tmp_path, sphere):
    cfg = make_cfg(tmp_path, views=5, frames_per_pose=2, settle_s=0.03)

    async def scenario():
        async with daemon_runner(cfg, sphere, frame_time_s=0.02, motion_time_s=0.05) as runner:
            arm = runner.arm
            await runner.start("settle")
            await until(lambda: runner.job is not None and runner.job.dropped > 0, "a dropped frame")
            await runner.wait("settle")
            return list(arm.stops)

    stops = arun(scenario())
    data = check_capture(tmp_path / "caps" / "settle", 5, 2)
    for m in data.meta:
        assert m["t_start"] >= stops[m["pose_index"]] + 0.03 - 1e-9


def test_pause_resume_abort(arun, tmp_path, sphere, caplog):
    caplog.set_level(logging.INFO, logger="spadscan.daemon")
    cfg = make_cfg(tmp_path, views=30, frames_per_pose=1)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("p")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            assert (await runner.pause())["state"] in ("pausing", "paused")
            await until(lambda: runner.state == "paused", "paused")
            held = runner.job.next_pose
            await asyncio.sleep(0.1)
            assert runner.job.next_pose == held and runner.status()["reason"] == "paused by user"
            await runner.resume()
            await until(lambda: runner.job.next_pose >= held + 3, "progress after resume")
            reply = await runner.abort("enough")
            assert reply["aborted"] == "p" and reply["state"] == "idle"
            waited = await runner.wait("p")
            # A new scan can start after an abort.
            await runner.start("q", {"views": 3})
            return held, waited, await runner.wait("q")

    held, waited, second = arun(scenario())
    assert waited == {"name": "p", "state": "aborted"} and second["state"] == "complete"
    r = CaptureReader(tmp_path / "caps" / "p")
    assert r.state == "aborted" and r.manifest["reason"] == "enough"
    idx = r.load().pose_indices.tolist()
    assert idx == list(range(len(idx))) and held + 3 <= len(idx) < 30  # a prefix, each pose once
    check_capture(tmp_path / "caps" / "q", 3, 1)
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert any(m.startswith("scan p: pause requested at pose") for m in said), said
    assert any(m == f"scan p paused by user at pose {held}/30" for m in said), said
    assert any(m.startswith(f"scan p: resumed at pose {held}/30 (was paused: paused by user)") for m in said), said


@pytest.mark.parametrize("lost", [("chunk-000001",), ("chunk-000001", "chunk-000003")])
def test_chunks_lost_while_the_scan_runs_are_taken_again_before_it_is_complete(arun, tmp_path, sphere, caplog, lost):
    """A chunk moved out or deleted while the scan runs (not paused): "complete" promises every pose, so the poses
    it held are taken again, in pose order, before the scan is called complete, and the log says which."""
    caplog.set_level(logging.INFO, logger="spadscan.daemon")
    cfg = make_cfg(tmp_path, views=8, frames_per_pose=2, chunk_size=2)  # a chunk a pose
    folder = tmp_path / "caps" / "gone"

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            take_frame, arm = runner.sensor.next_frame, runner.arm

            async def next_frame(timeout_s):
                if arm.moves == 6 and all((folder / name).exists() for name in lost):  # at pose 5, once
                    for name in lost:
                        await runner._io(shutil.rmtree, folder / name)
                return await take_frame(timeout_s)

            runner.sensor.next_frame = next_frame
            await runner.start("gone")
            return await runner.wait("gone"), runner.status()

    done, status = arun(scenario())
    assert done == {"name": "gone", "state": "complete"} and status.get("poses_to_take_again") in (None, [])
    check_capture(folder, 8, 2)
    said = [r.getMessage() for r in caplog.records if "gone from its folder" in r.getMessage()]
    poses = ", ".join(name[-1] for name in lost)
    assert said == [f"scan gone: {', '.join(lost)} gone from its folder (moved out or deleted while the scan ran): "
                    f"taking pose(s) {poses} again before the scan is complete"], said


def test_a_scan_folder_deleted_while_the_scan_runs_pauses_it_naming_that_not_the_disk(arun, tmp_path, sphere):
    cfg = make_cfg(tmp_path, views=8, frames_per_pose=1)
    folder = tmp_path / "caps" / "deleted"

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            take_frame, arm = runner.sensor.next_frame, runner.arm

            async def next_frame(timeout_s):
                if arm.moves == 4 and folder.exists():
                    await runner._io(shutil.rmtree, folder)  # between two writes, as `rm -r` may fall
                return await take_frame(timeout_s)

            runner.sensor.next_frame = next_frame
            status = await paused_after(runner, "deleted", lambda: None, poses=0)
            with pytest.raises(ConfigError) as busy:  # a new scan is refused, the reason told again
                await runner.start("next")
            await runner.abort("gone")
            return status, str(busy.value)

    status, busy = arun(scenario())
    assert busy.startswith("scan 'deleted' is paused at pose ") and busy.endswith(
        f"({status['reason']}): resume or abort it first"), busy
    assert f"the scan's folder {folder} is gone (moved or deleted while the scan ran): move it back, then `spadscan " \
           f"ctl resume`, or `spadscan ctl abort` ends the scan" in status["reason"], status
    assert "disk" not in status["reason"], status


class RestartingSensor(SimSensor):
    """A sensor that starts again on its own once `restart(s)` is called (a bridge set up afresh after a replug): no
    frame for `s` seconds, which `starting_left` says while it lasts."""

    until: float | None = None

    def restart(self, seconds: float) -> None:
        self.until = time.monotonic() + seconds

    def starting_left(self) -> float:
        return 0.0 if self.until is None else max(0.0, self.until - time.monotonic())

    async def next_frame(self, timeout_s):
        left = self.starting_left()
        if left > timeout_s:
            await asyncio.sleep(timeout_s)
            raise SensorSilent(f"{self.name}: no complete frame within {timeout_s:g} s")
        await asyncio.sleep(left)
        self.until = None
        return await super().next_frame(timeout_s)


def test_a_sensor_starting_again_on_its_own_is_waited_for_once_not_paused(arun, tmp_path, sphere, caplog):
    """Its start lasts three frame timeouts: the wait is begun again once, for the rest of the start and then a
    frame timeout, and said once; the scan never pauses."""
    cfg = make_cfg(tmp_path, views=6, frames_per_pose=1, frame_timeout_s=0.5)
    arm = TimedArm(motion_time_s=0.0)
    sensor = RestartingSensor(sensor_preset("tmf8820"), sphere, pose_provider(arm, cfg.arm.hand_eye),
                              settings=SimSettings(rays_per_zone=16), seed=1)

    async def scenario():
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                moved = arm.move_to

                async def move_to(*args):
                    await moved(*args)
                    if arm.moves == 3:
                        sensor.restart(1.5)

                arm.move_to = move_to
                await runner.start("restart")
                states = []
                while runner.job is not None and runner.job.name == "restart" and runner.state != "idle":
                    states.append(runner.state)
                    await asyncio.sleep(0.01)
                return await runner.wait("restart"), states
            finally:
                await runner.shutdown()

    done, states = arun(scenario())
    assert done == {"name": "restart", "state": "complete"} and "paused" not in states
    said = [r.getMessage() for r in caplog.records if "is starting again" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("scan restart: the sensor is starting again"), said
    check_capture(tmp_path / "caps" / "restart", 6, 1)


def test_the_first_move_after_a_resume_is_checked_like_every_planned_one(arun, tmp_path, sphere):
    """While paused, the arm is jogged out of the workspace, under the box and across the base from the scan. The
    straight move back would pass close to the base: resuming refuses it with the reason and moves nothing; once the
    arm is back near the next pose, resuming goes on."""
    limits = {"workspace_min": [-0.8, -0.8, 0.08], "workspace_max": [0.8, 0.8, 0.8], "min_reach_m": 0.2}
    cfg = make_cfg(tmp_path, views=12, frames_per_pose=1, target=[0.4, 0.0, 0.1], radius_m=0.25, arm=limits)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            arm = runner.arm
            await runner.start("jog")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            await runner.pause()
            await until(lambda: runner.state == "paused", "paused")
            moves = arm.moves
            arm.jog(np.array([[1.0, 0, 0, -0.35], [0, -1, 0, 0], [0, 0, -1, 0.04], [0, 0, 0, 1]]))
            await runner.resume()
            await until(lambda: runner.state == "paused" and runner.job.reason, "the refusal")
            refused, moved = runner.status(), arm.moves - moves
            arm.jog(runner.job.tcp_poses[runner.job.next_pose])  # the operator brings it back
            await runner.resume()
            return refused, moved, await runner.wait("jog")

    refused, moved, done = arun(scenario())
    reason = refused["reason"]
    assert moved == 0 and refused["state"] == "paused"
    assert "at [-0.350, 0.000, 0.040] m is not moved to pose" in reason and "z = 0.040 m is below workspace_min" in reason
    assert "jog it back into the workspace" in reason and "\n" not in reason
    assert done["state"] == "complete"
    check_capture(tmp_path / "caps" / "jog", 12, 1)


def test_a_first_move_through_the_base_is_refused_even_from_inside_the_workspace(arun, tmp_path, sphere):
    """Jogged to the far side of the base, inside the box: the straight move back passes within min_reach_m."""
    limits = {"workspace_min": [-0.8, -0.8, 0.0], "workspace_max": [0.8, 0.8, 0.8], "min_reach_m": 0.2}
    cfg = make_cfg(tmp_path, views=6, frames_per_pose=1, target=[0.4, 0.0, 0.05], radius_m=0.2, arm=limits)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            arm = runner.arm
            await runner.start("across")
            await until(lambda: runner.job.next_pose >= 1, "a pose")
            await runner.pause()
            await until(lambda: runner.state == "paused", "paused")
            target = runner.job.tcp_poses[runner.job.next_pose]
            across = target.copy()
            across[:3, 3] = [-target[0, 3], -target[1, 3], 0.05]  # mirrored through the base's axis, low
            arm.jog(across)
            await runner.resume()
            await until(lambda: runner.state == "paused" and runner.job.reason, "the refusal")
            reason = runner.status()["reason"]
            await runner.abort("done")
            return reason

    reason = arun(scenario())
    assert "the straight move there passes" in reason and "from the base, inside min_reach_m 0.2" in reason


def test_protective_stop_pauses_with_reason_and_resume_clears_it(arun, tmp_path, sphere):
    """The sim arm's injected protective stop pauses the scan; `resume` clears it (Arm.clear_fault: the sim's stand-in
    for the operator at the pendant) and the scan completes, every pose once."""
    cfg = make_cfg(tmp_path, views=8)

    async def scenario():
        async with daemon_runner(cfg, sphere, faults=SimArmFaults(protective_stop_on_moves=(4,))) as runner:
            arm = runner.arm
            await runner.start("stop")
            await until(lambda: runner.state == "paused", "the pause")
            first = runner.status()
            stopped = arm.protective_stop
            await runner.resume()
            return first, stopped, await runner.wait("stop"), arm.moves

    first, stopped, done, moves = arun(scenario())
    assert "protective stop" in first["reason"] and first["reason"] == first["last_error"]
    assert first["pose"] == 3 and first["progress"] == "3/8"
    assert stopped and done["state"] == "complete"
    assert moves == 9  # the stopped move, once more after resume
    check_capture(tmp_path / "caps" / "stop", 8, 2)


@pytest.mark.parametrize("kind", [PROTECTIVE_STOP, SAFEGUARD_STOP, EMERGENCY_STOP])
def test_a_safety_stop_while_the_arm_stands_at_a_pose_is_named_with_what_clears_it(arun, tmp_path, sphere, kind):
    """The stop comes while the sensor captures pose 2 (the arm at rest, where a scan spends most of its time): the
    pause names that stop, not another (the operator clears each in its own way), says what clears it, and resume
    completes the scan."""
    cfg = make_cfg(tmp_path, views=6)

    async def scenario():
        arm, sensor = make_rig(cfg, sphere)
        take_frame, pending = sensor.next_frame, [kind]

        async def next_frame(timeout_s):
            if arm.moves == 3 and pending:  # pose 2's frames: the arm stands at the pose
                arm.trigger_stop(pending.pop())
            return await take_frame(timeout_s)

        sensor.next_frame = next_frame
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                await runner.start("held")
                return await resumed_after_pause(runner, "held")
            finally:
                await runner.shutdown()

    reason, done = arun(scenario())
    assert reason == f"arm fault: {kind} on arm (sim) while capturing pose 2; {TO_CLEAR[kind]}, then resume (pose 2/6)"
    assert done["state"] == "complete"
    check_capture(tmp_path / "caps" / "held", 6, 2)


@pytest.mark.parametrize("paused_by", ["user", "arm fault"])
def test_a_link_that_dropped_and_came_back_while_paused_is_reconnected_by_the_first_resume(arun, tmp_path, sphere,
                                                                                           paused_by):
    """The link drops while the scan is paused for something else (a controller rebooted, a cable re-plugged) and
    comes back before the operator resumes: the first resume reconnects it and the scan completes, instead of
    pausing again for a lost link that is no longer lost."""
    cfg = make_cfg(tmp_path, views=6)
    faults = SimArmFaults(protective_stop_on_moves=(3,) if paused_by == "arm fault" else ())

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.02, faults=faults) as runner:
            arm = runner.arm
            await runner.start("relink")
            if paused_by == "user":
                await until(lambda: runner.job.next_pose >= 2, "two poses")
                await runner.pause()
            await until(lambda: runner.state == "paused", "the pause")
            reason = runner.status()["reason"]
            arm.drop_link()
            arm.restore_link()
            await runner.resume()
            await until(lambda: runner.state in ("idle", "paused"), "the resumed scan to end or pause")
            return reason, runner.status(), arm.connected

    reason, status, connected = arun(scenario())
    assert reason.startswith("paused by user" if paused_by == "user" else "arm fault: arm (sim): protective stop")
    assert status["state"] == "idle" and status["last_scan"] == {"name": "relink", "state": "complete"}, status
    assert connected
    check_capture(tmp_path / "caps" / "relink", 6, 2)


def test_a_fault_soon_after_the_daemon_stood_still_says_so(arun, tmp_path, sphere):
    """The event loop stands still for 1.2 s (as in a SIGSTOP), then the arm stops protectively: the reason names
    the arm's fault and adds that the daemon itself had not run (a watchdog may have stopped the arm for that)."""
    cfg = make_cfg(tmp_path, views=8)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            arm = runner.arm
            await runner.start("still")
            await until(lambda: runner.job.next_pose >= 1, "a pose")
            time.sleep(1.2)  # the whole loop stands still
            arm.trigger_protective_stop()
            await until(lambda: runner.state == "paused", "the pause")
            status = runner.status()
            await runner.abort()
            return status

    status = arun(scenario())
    assert "protective stop" in status["reason"], status["reason"]
    stood = re.search(r"; the daemon itself had not run for ([\d.]+) s", status["reason"])
    assert stood and float(stood[1]) >= 1.1, status["reason"]  # 1.2 s standing still, and what load adds to it
    assert status["daemon_stalls"]["count"] >= 1


@pytest.mark.parametrize("frame_time_s", [0.0, 0.05])
def test_sensor_silence_pauses_and_resumes(arun, tmp_path, sphere, frame_time_s):
    """With frames that take time, the frame exposed while the arm moved is dropped at every pose: a silence after
    it is still a silence."""
    # A timeout well beyond a frame's time, so that a busy machine's scheduling delay is no silence.
    cfg = make_cfg(tmp_path, views=8, frame_timeout_s=1.0)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.03, frame_time_s=frame_time_s) as runner:
            sensor = runner.sensor
            await runner.start("quiet")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            quiet_until = time.monotonic() + 3.0
            sensor.inject_silence(3.0)
            await until(lambda: runner.state == "paused", "the pause")
            paused = runner.status()
            await asyncio.sleep(max(0.0, quiet_until - time.monotonic()) + 0.1)  # the silence is over
            await runner.resume()
            return paused, await runner.wait("quiet")

    paused, done = arun(scenario())
    assert paused["reason"].startswith("sensor silent: sensor sim: no complete frame within 1 s (frame_timeout_s) "
                                       "at pose "), paused["reason"]  # the configured timeout, not what was left of it
    # The reason and the counters agree: the sensor counted its silence, the daemon did not stall (the frames dropped
    # at each pose, begun while the arm moved, do not make a silence a backlog).
    assert paused["sensor"]["silent_timeouts"] >= 1 and paused["daemon_stalls"]["frame_waits_retried"] == 0
    assert done["state"] == "complete"
    check_capture(tmp_path / "caps" / "quiet", 8, 2)


class StaleSensor(SimSensor):
    """Delivers frames that all began long ago (a backlog that never drains)."""

    async def next_frame(self, timeout_s):
        frame = await super().next_frame(timeout_s)
        frame.t_start = -1.0
        return frame


def test_frames_that_all_began_too_early_are_not_called_a_silent_sensor(arun, tmp_path, sphere):
    cfg = make_cfg(tmp_path, views=4, frame_timeout_s=0.3)

    async def scenario():
        arm = TimedArm(motion_time_s=0.0)
        sensor = StaleSensor(sensor_preset("tmf8820"), sphere, pose_provider(arm, cfg.arm.hand_eye),
                             settings=SimSettings(rays_per_zone=16), seed=1, frame_time_s=0.02)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                await runner.start("stale")
                await until(lambda: runner.state == "paused", "the pause")
                status = runner.status()
                await runner.abort()
                return status
            finally:
                await runner.shutdown()

    status = arun(scenario())
    assert status["reason"].startswith("sensor sim: ") and "sensor silent" not in status["reason"]
    assert "frames in 0.3 s (frame_timeout_s) at pose 0, none begun after the arm settled" in status["reason"]
    assert status["dropped_frames"] > 0


def test_disk_full_pauses_and_loses_nothing_published(arun, tmp_path, sphere, monkeypatch):
    import spadscan.protocol.capture_writer as cw

    cfg = make_cfg(tmp_path, views=10)
    real = cw.save_npy_durable
    full = {"on": False}

    def save(path, array):
        if full["on"] and path.name == "poses.npy":  # the chunk's second file: a half-written chunk
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real(path, array)

    monkeypatch.setattr(cw, "save_npy_durable", save)
    folder = tmp_path / "caps" / "full"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("full")
            await until(lambda: runner.job.next_pose >= 3, "three poses")
            full["on"] = True
            await until(lambda: runner.state == "paused", "the pause")
            paused = runner.status()
            snapshot = {p.relative_to(folder): p.read_bytes() for p in folder.glob("chunk-*/*")}
            await runner.resume()  # still full: pauses again, nothing lost
            await until(lambda: runner.state == "paused", "the second pause")
            full["on"] = False
            await runner.resume()
            return paused, snapshot, await runner.wait("full")

    paused, snapshot, done = arun(scenario())
    assert paused["reason"].startswith("disk full while publishing") and "No space left" in paused["reason"]
    assert done["state"] == "complete"
    check_capture(folder, 10, 2)
    for rel, data in snapshot.items():  # every file published before the fault is still there, unchanged
        assert (folder / rel).read_bytes() == data
    assert not list(folder.glob(".tmp-*"))


def test_disk_full_at_scan_start_is_refused_and_the_name_stays_free(arun, tmp_path, sphere, monkeypatch):
    import spadscan.protocol.capture_writer as cw

    cfg = make_cfg(tmp_path, views=4)
    real = cw.save_npy_durable
    full = {"on": True}

    def save(path, array):
        if full["on"]:  # schedule.npy: the folder exists, the manifest does not
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real(path, array)

    monkeypatch.setattr(cw, "save_npy_durable", save)

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            with pytest.raises(CaptureError) as refused:
                await runner.start("late")
            after = runner.status()
            left = (tmp_path / "caps" / "late").exists()
            full["on"] = False
            await runner.start("late")
            return str(refused.value), after, left, await runner.wait("late")

    refused, after, left, done = arun(scenario())
    assert refused.startswith("cannot start scan 'late': disk full") and "No space left" in refused, refused
    assert after["state"] == "idle" and after["last_error"] == refused
    assert not left, "the half-made scan folder was left behind"
    assert done["state"] == "complete"
    check_capture(tmp_path / "caps" / "late", 4, 2)


def test_link_loss_pauses_and_resumes(arun, tmp_path, sphere):
    cfg = make_cfg(tmp_path, views=6)

    async def scenario():
        async with daemon_runner(cfg, sphere, faults=SimArmFaults(link_drop_on_moves=(2,))) as runner:
            arm = runner.arm
            await runner.start("link")
            return await resumed_after_pause(runner, "link", arm.restore_link)

    reason, done = arun(scenario())
    assert reason.startswith("link lost: arm (sim)")
    assert done["state"] == "complete"
    check_capture(tmp_path / "caps" / "link", 6, 2)


def test_restart_takes_over_an_interrupted_scan(arun, tmp_path, sphere):
    cfg = make_cfg(tmp_path, views=12)
    auto = make_cfg(tmp_path, views=12, auto_resume=True)

    async def first_daemon():
        arm, sensor = make_rig(cfg, sphere, motion_time_s=0.01)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            await runner.start("crash")
            await until(lambda: runner.job.next_pose >= 4, "four poses")
            await runner.shutdown()  # like SIGTERM: the capture stays 'running'

    async def second_daemon(c, resume: bool):
        arm, sensor = make_rig(c, sphere)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, c)
            try:
                await runner.recover()
                first = runner.status()
                if resume:
                    await runner.resume()
                return first, await runner.wait("crash")
            finally:
                await runner.shutdown()

    arun(first_daemon())
    r = CaptureReader(tmp_path / "caps" / "crash")
    assert r.state == "running" and "daemon stopped" in r.manifest["reason"]
    n_before = len(r.load().meta)
    first, done = arun(second_daemon(cfg, resume=True))
    assert first["state"] == "paused" and "interrupted at pose" in first["reason"]
    assert first["frames"] == n_before and done["state"] == "complete"
    check_capture(tmp_path / "caps" / "crash", 12, 2)
    # auto_resume: the next interrupted scan continues by itself.
    (tmp_path / "caps" / "crash" / "scan.json").write_text(
        (tmp_path / "caps" / "crash" / "scan.json").read_text().replace('"complete"', '"running"'))
    first, done = arun(second_daemon(auto, resume=False))
    assert first["state"] in ("scanning", "idle") and done["state"] == "complete"
    check_capture(tmp_path / "caps" / "crash", 12, 2)


def test_restart_on_a_full_disk_takes_the_scan_over_paused(arun, tmp_path, sphere, monkeypatch):
    import spadscan.protocol.capture_writer as cw

    cfg = make_cfg(tmp_path, views=8, auto_resume=True)
    folder = tmp_path / "caps" / "crash"
    full = switchable_full_disk(monkeypatch, cw, "write_json_atomic")

    async def scenario():
        arm, sensor = make_rig(cfg, sphere, motion_time_s=0.01)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, make_cfg(tmp_path, views=8))
            await runner.start("crash")
            await until(lambda: runner.job.next_pose >= 3, "three poses")
            await runner.shutdown()
        published = {p.relative_to(folder): p.read_bytes() for p in folder.glob("chunk-*/*")}
        full["on"] = True
        arm, sensor = make_rig(cfg, sphere)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)  # auto_resume: not while the capture cannot be reopened
            try:
                await runner.recover()
                first = runner.status()
                full["on"] = False
                await runner.resume()
                return published, first, await runner.wait("crash")
            finally:
                await runner.shutdown()

    published, first, done = arun(scenario())
    assert first["state"] == "paused" and first["scan"] == "crash", first
    assert "disk full while reopening the capture" in first["reason"] and "No space left" in first["reason"], first
    assert first["pose"] >= 3 and first["frames"] == len(CaptureReader(folder).load().meta) - 2 * (8 - first["pose"])
    assert done["state"] == "complete"
    check_capture(folder, 8, 2)
    for rel, data in published.items():
        assert (folder / rel).read_bytes() == data


def test_requests_in_the_wrong_state_are_refused(arun, tmp_path, sphere):
    cfg = make_cfg(tmp_path, views=40)
    (tmp_path / "caps").mkdir()
    (tmp_path / "caps" / "taken").mkdir()

    async def scenario():
        arm, sensor = make_rig(cfg, sphere, motion_time_s=0.01)
        errors = []
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                for call in (runner.pause(), runner.resume(), runner.abort(), runner.wait("ghost"),
                             runner.start("taken"), runner.start("../up"), runner.start("a/b"), runner.start(".hid"),
                             runner.start(""), runner.start("ok", {"views": 0}), runner.start("ok", {"fps": 2})):
                    with pytest.raises(ConfigError) as info:
                        await call
                    errors.append(str(info.value))
                # Two clients asking at once: exactly one scan starts.
                both = await asyncio.gather(runner.start("busy"), runner.start("twin"), return_exceptions=True)
                assert isinstance(both[1], ConfigError) and both[0]["scan"] == "busy"
                with pytest.raises(ConfigError, match="'busy' is scanning"):
                    await runner.start("other")
                await runner.abort()
            finally:
                await runner.shutdown()
        return errors

    errors = arun(scenario())
    assert all("\n" not in e for e in errors)
    assert "nothing to pause" in errors[0] and "nothing to resume" in errors[1] and "nothing to abort" in errors[2]
    assert "no scan named 'ghost'" in errors[3]
    assert errors[4] == (f"'taken' already exists in {tmp_path / 'caps'}, a folder that holds no scan (choose another "
                         f"name)")
    assert all("scan name" in e for e in errors[5:9])
    assert "views" in errors[9] and "unknown key 'fps'" in errors[10]
    assert sorted(p.name for p in (tmp_path / "caps").iterdir()) == ["busy", "taken"]


def test_stalled_disk_pauses_and_the_late_write_is_kept(arun, tmp_path, sphere, monkeypatch):
    import spadscan.daemon.runner as runner_mod
    import spadscan.protocol.capture_writer as cw

    monkeypatch.setattr(runner_mod, "PUBLISH_TIMEOUT_S", 5.0)  # a loaded machine's fsync stays well inside it
    cfg = make_cfg(tmp_path, views=6)
    real = cw.save_npy_durable
    stall = {"once": False}
    disk_back = threading.Event()

    def save(path, array):
        if stall["once"]:
            stall["once"] = False
            disk_back.wait(120)  # a disk that stalls until the test has seen the pause, then completes the write
        real(path, array)

    monkeypatch.setattr(cw, "save_npy_durable", save)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("stall")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            stall["once"] = True
            return await resumed_after_pause(runner, "stall", disk_back.set)

    reason, done = arun(scenario())
    assert "did not finish within 5 s" in reason and done["state"] == "complete"
    check_capture(tmp_path / "caps" / "stall", 6, 2)


def test_only_scans_the_daemon_wrote_are_taken_over(arun, tmp_path, sphere, caplog):
    """An interrupted capture another tool wrote under the captures root (here a 'running' capture with a schedule,
    as `spadscan simulate --out <captures>/x` leaves one) is logged and skipped, even with auto_resume and even
    when it is the newest; the daemon's own interrupted scan is taken over (and that is logged)."""
    caplog.set_level(logging.INFO, logger="spadscan.daemon")
    cfg = make_cfg(tmp_path, views=6, auto_resume=True)

    async def daemon(start: str | None):
        async with daemon_runner(cfg, sphere) as runner:
            arm = runner.arm
            if start:
                await runner.start(start)
                await until(lambda: runner.job.next_pose >= 2, "two poses")
                return runner.status()
            await runner.recover()
            status = runner.status()
            if status["scan"] is not None:
                await runner.wait(status["scan"])
            return status, arm.moves

    def foreign(name: str) -> Path:
        planned = CaptureReader(tmp_path / "caps" / "mine").planned_poses() if name == "sim-later" else None
        w = CaptureWriter.create(tmp_path / "caps" / name, sensor_preset("tmf8820"), rig={"kind": "simulated"},
                                 planned_poses=planned if planned is not None else np.eye(4)[None])
        return w.path

    (tmp_path / "caps").mkdir()
    foreign("sim-first")
    status, moves = arun(daemon(None))  # only someone else's capture: nothing taken over, nothing moves
    assert status["state"] == "idle" and status["scan"] is None and moves == 0
    assert any("not taking over" in r.getMessage() and "sim-first" in r.getMessage() for r in caplog.records)
    arun(daemon("mine"))  # stopped mid-scan: stays 'running'
    foreign("sim-later")  # newer than the daemon's, with a full schedule of its own
    status, _ = arun(daemon(None))
    assert status["scan"] == "mine"
    check_capture(tmp_path / "caps" / "mine", 6, 2)
    for name in ("sim-first", "sim-later"):
        r = CaptureReader(tmp_path / "caps" / name)
        assert r.state == "running" and r.chunk_names() == []  # untouched
    assert CaptureReader(tmp_path / "caps" / "mine").manifest["rig"]["writer"] == "spadscan-daemon"
    assert any(r.getMessage().startswith("took over interrupted scan mine at pose ") for r in caplog.records)


def test_a_new_scans_name_taken_says_by_what(arun, tmp_path, sphere):
    """`ctl scan --name X` called a file X, or a folder X that holds no scan, a scan that exists, where `ctl wait X`
    said there is no scan named X."""
    cfg = make_cfg(tmp_path, views=4, frames_per_pose=1)
    caps = tmp_path / "caps"
    caps.mkdir()
    (caps / "notes").write_text("keep")

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.start("done")
            await runner.wait("done")
            said = []
            for name in ("notes", "done"):
                with pytest.raises(ConfigError) as refused:
                    await runner.start(name)
                said.append(str(refused.value))
            return said

    assert arun(scenario()) == [f"'notes' already exists in {caps}, a file, not a scan (choose another name)",
                                f"scan 'done' already exists in {caps} (choose another name)"]
    assert (caps / "notes").read_text() == "keep"


def test_a_folder_that_appears_while_a_scan_is_planned_is_left_alone(arun, tmp_path, sphere, monkeypatch):
    """The scan's folder is made exclusively once its plan is ready: one that another program made meanwhile is
    refused and kept as it is, never filled nor removed."""
    import spadscan.daemon.runner as runner_module

    cfg = make_cfg(tmp_path, views=4, frames_per_pose=1)
    theirs = tmp_path / "caps" / "raced"
    real = runner_module.build_plan

    def plan_while_another_program_writes(*args, **kwargs):
        theirs.mkdir(parents=True)
        (theirs / "theirs.txt").write_text("keep")
        return real(*args, **kwargs)

    monkeypatch.setattr(runner_module, "build_plan", plan_while_another_program_writes)

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            with pytest.raises(ConfigError, match="already exists"):
                await runner.start("raced")

    arun(scenario())
    assert sorted(p.name for p in theirs.iterdir()) == ["theirs.txt"]
