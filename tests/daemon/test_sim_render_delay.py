"""A simulated sensor whose renders our own process is slow to produce (a loaded machine starves the render thread)
is not taken for a silent sensor: the frame timeout, its own and the runner's frame_timeout_s, counts on the sensor's
wait clock, which stands still from the moment a frame is due until it is handed over. Silence still pauses the scan.

The render is slowed on purpose (`SlowSim`: each render sleeps on its thread, as a starved one takes long), longer
than every timeout in play, so that no machine is fast enough to hide the fault."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.backends import pose_provider
from spadscan.daemon.devices import SensorSilent
from spadscan.daemon.runner import FRAME_GRACE_S, ScanRunner
from spadscan.daemon.sensor.sim import HOLD_TIMEOUTS, SimSensor
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings

from test_runner import TimedArm, check_capture, make_cfg, sphere, until  # noqa: F401  (sphere: a fixture)


class SlowSim(SimSensor):
    """A SimSensor whose renders take `delays` seconds on their thread, one delay per render in turn (0 after the
    list ends)."""

    def __init__(self, *args, delays=(), **kw):
        super().__init__(*args, **kw)
        self.delays = list(delays)
        self.renders = 0

    def _render(self, pose):
        delay = self.delays[self.renders] if self.renders < len(self.delays) else 0.0
        self.renders += 1
        time.sleep(delay)  # the fault injected: this process takes that long to produce the frame
        return super()._render(pose)


def looking_at_the_sphere():
    pose = np.eye(4)
    pose[2, 3] = -0.5  # 0.5 m below the sphere's centre, looking up its +z
    return pose


@pytest.mark.parametrize("frame_time_s", [0.0, 0.05])
def test_a_render_slower_than_the_timeout_still_delivers_its_frame(arun, sphere, frame_time_s):  # noqa: F811
    """Renders of 0.6 s against a timeout of 0.1 s beyond the frame time: both frames arrive, and the wait clock
    counted only the frames' own exposure (a real sensor's frame comes frame_time_s after it began, whatever our CPU
    does); the sensor's counters say how long its frames were late for this process's sake."""
    sensor = SlowSim(sensor_preset("tmf8820"), sphere, looking_at_the_sphere, settings=SimSettings(rays_per_zone=16),
                     delays=(0.6, 0.6), frame_time_s=frame_time_s)

    async def scenario():
        await sensor.prepare()
        try:
            wall, clock = time.monotonic(), sensor.wait_clock()
            frames = [await sensor.next_frame(0.1 + frame_time_s) for _ in range(2)]
            return frames, time.monotonic() - wall, sensor.wait_clock() - clock
        finally:
            await sensor.release()

    frames, wall_s, clock_s = arun(scenario())
    assert len(frames) == 2 and sensor.counters()["silent_timeouts"] == 0
    assert wall_s >= 1.2 and clock_s < 0.2 + 2 * frame_time_s, (wall_s, clock_s)
    # (status shows it: the machine was slow, not the sensor)
    assert sensor.counters()["late_render_s"] >= 1.2 - 2 * frame_time_s


def test_silence_still_times_out_on_the_wait_clock(arun, sphere):  # noqa: F811
    """The clock stands still only while a frame is produced: an injected silence passes on it as on the wall."""
    sensor = SlowSim(sensor_preset("tmf8820"), sphere, looking_at_the_sphere, settings=SimSettings(rays_per_zone=16))

    async def scenario():
        await sensor.prepare()
        try:
            sensor.inject_silence(30.0)
            with pytest.raises(SensorSilent):
                await sensor.next_frame(0.2)
        finally:
            await sensor.release()

    arun(scenario())
    assert sensor.counters()["silent_timeouts"] == 1


def test_a_scan_whose_renders_outlast_every_timeout_completes_without_a_pause(arun, tmp_path, sphere):  # noqa: F811
    """frame_timeout_s 0.3 (what `daemon --check` accepts) and a first render that takes longer than it and the
    runner's own grace beyond it (FRAME_GRACE_S), then renders of 0.5 s: the scan completes, never paused as a silent
    sensor, and the capture holds every pose."""
    cfg = make_cfg(tmp_path, views=3, frames_per_pose=1, frame_timeout_s=0.3)
    arm = TimedArm(motion_time_s=0.0)
    sensor = SlowSim(sensor_preset("tmf8820"), sphere, pose_provider(arm, cfg.arm.hand_eye),
                     settings=SimSettings(rays_per_zone=16), seed=1, delays=(0.3 + FRAME_GRACE_S + 0.3, 0.5, 0.5))

    async def scenario():
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                await runner.start("loaded")
                await until(lambda: runner.state in ("idle", "paused"), "the scan to end or pause", 60.0)
                return runner.status()
            finally:
                await runner.shutdown()

    status = arun(scenario())
    assert status["state"] == "idle" and status["last_scan"] == {"name": "loaded", "state": "complete"}, status
    assert sensor.renders == 3 and sensor.counters()["silent_timeouts"] == 0
    check_capture(tmp_path / "caps" / "loaded", 3, 1)


class BlockedSim(SimSensor):
    """A SimSensor whose render never returns until `release` is set (a deadlocked library, a saturated executor);
    `rendering` is set once it has begun. One frame may hold its wait clock still for 0.5 s or ten timeouts."""

    hold_min_s = 0.5

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self.rendering, self.release_render = threading.Event(), threading.Event()

    def _render(self, pose):
        self.rendering.set()
        self.release_render.wait()
        return super()._render(pose)


def test_a_render_that_never_returns_still_times_out(arun, sphere):  # noqa: F811
    """The wait clock stood still from a frame's due time until its hand-over with no bound: a render that never
    returned never raised SensorSilent, and the scan sat in "scanning" for ever. One frame now holds the clock for at
    most max(hold_min_s, HOLD_TIMEOUTS x the timeout), after which the timeout fires (and says why). The bound on the
    wait is a guard against the hang alone, far beyond the 1.1 s of clock and wall it takes."""
    sensor = BlockedSim(sensor_preset("tmf8820"), sphere, looking_at_the_sphere, settings=SimSettings(rays_per_zone=16))

    async def scenario():
        await sensor.prepare()
        try:
            with pytest.raises(SensorSilent, match="held the wait for 1 s") as raised:
                await asyncio.wait_for(sensor.next_frame(0.1), 60.0)
            assert "held the wait for 1 s" in raised.value.detail, "the runner's pause reason keeps the detail"
            assert sensor.rendering.is_set()
        finally:
            sensor.release_render.set()  # the render's thread ends, so that the event loop can close
            await sensor.release()

    arun(scenario())
    assert sensor.counters()["silent_timeouts"] == 1
    assert sensor.counters()["late_render_s"] == pytest.approx(HOLD_TIMEOUTS * 0.1)
