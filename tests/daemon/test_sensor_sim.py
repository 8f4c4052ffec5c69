"""SimSensor: plausible frames at the pose it is given, the real sensor's back-to-back frame timing, faults."""

from __future__ import annotations

import asyncio
import math
import threading
import time

import numpy as np
import pytest
import trimesh

from spadscan.daemon.devices import LinkLost, SensorSilent
from spadscan.daemon.sensor.sim import SimSensor
from spadscan.protocol.errors import DeviceError
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings

FAST = SimSettings(rays_per_zone=256)


@pytest.fixture(autouse=True)
def no_leaked_threads():
    before = set(threading.enumerate())
    yield
    assert not set(threading.enumerate()) - before, "test leaked threads"


def floor_plane():
    """A 4 m x 4 m floor at z = 0."""
    return trimesh.Trimesh(vertices=[[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], faces=[[0, 1, 2], [0, 2, 3]])


def looking_down(height_m):
    """Sensor pose (4, 4) at (0, 0, height) looking along world -z (its +z)."""
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
    pose[2, 3] = height_m
    return pose


async def frames_of(sensor, n, timeout_s=10.0):
    await sensor.connect()
    await sensor.prepare()
    try:
        return [await sensor.next_frame(timeout_s) for _ in range(n)]
    finally:
        await sensor.release()
        await sensor.close()


def test_tmf8820_frame_of_a_floor_peaks_at_its_range(arun):
    model = sensor_preset("tmf8820")
    sensor = SimSensor(model, floor_plane(), lambda: looking_down(0.5), settings=FAST)
    (f,) = arun(frames_of(sensor, 1))
    assert f.hists.shape == (9, 128) and f.hists.dtype == np.uint32 and f.reference.shape == (128,)
    peaks = f.hists.argmax(axis=1)
    centre = model.bin_of_range(0.5)  # the centre zone looks straight down
    assert centre - 1 <= peaks[4] <= centre + 4
    # Corner zones look up to ~22 degrees off the axis: their floor is farther, never nearer.
    assert np.all(peaks >= peaks[4] - 1) and np.all(peaks <= model.bin_of_range(0.5 / math.cos(0.4)) + 4)
    assert abs(f.reference.argmax() - model.zero_bin) < 4  # the reference pulse sits near zero range


def test_lcspc_frame_of_a_sphere_peaks_at_its_surface(arun):
    model = sensor_preset("lcspc-sim")
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    sensor = SimSensor(model, ball, lambda: looking_down(0.5), settings=FAST, seed=3)
    (f,) = arun(frames_of(sensor, 1))
    assert f.hists.shape == (1, 1024) and f.reference is None
    peak = np.convolve(f.hists[0], np.ones(5), "same").argmax()  # 5,000 cycles: smooth the photon noise
    top = model.bin_of_range(0.4)  # 0.4 m to the top of the ball; 1.25 mm bins
    # The pulse's tail and the curved cap behind the top (more area at longer range) put the peak a little later.
    assert top - 2 <= peak <= top + 14


def test_each_frame_is_rendered_at_the_pose_when_it_starts(arun):
    model = sensor_preset("tmf8820")
    heights = iter([0.3, 0.6])
    calls = []

    def provider():
        calls.append(time.monotonic())
        return looking_down(next(heights))

    sensor = SimSensor(model, floor_plane(), provider, settings=FAST, frame_time_s=0.05)
    near, far = arun(frames_of(sensor, 2))
    assert len(calls) == 2 and near.t_start <= calls[0] < near.t_end and far.t_start <= calls[1] < far.t_end
    shift = far.hists[4].argmax() - near.hists[4].argmax()
    assert abs(shift - 0.3 / model.bin_width_m) <= 3
    assert near.extra["render_pose"][2][3] == 0.3


def test_frames_run_back_to_back_and_a_late_caller_gets_the_frame_in_progress(arun):
    t_frame = 0.2

    async def main():
        sensor = SimSensor(sensor_preset("tmf8820"), floor_plane(), lambda: looking_down(0.5), settings=FAST,
                           frame_time_s=t_frame)
        await sensor.prepare()
        a, b = await sensor.next_frame(5), await sensor.next_frame(5)
        # Ask in the middle of a frame: half a frame (0.1 s) from either edge, so scheduling delays do not matter.
        await asyncio.sleep(b.t_end + 2.5 * t_frame - time.monotonic())
        asked = time.monotonic()
        c = await sensor.next_frame(5)
        await sensor.release()
        return a, b, c, asked

    a, b, c, asked = arun(main())
    assert b.t_start == a.t_end and min(a.t_end - a.t_start, b.t_end - b.t_start) >= t_frame - 1e-9
    frames_skipped = (c.t_start - b.t_end) / t_frame
    assert c.t_start <= asked and frames_skipped >= 1 and abs(frames_skipped - round(frames_skipped)) < 1e-6


def test_silence_and_link_loss(arun):
    async def main():
        sensor = SimSensor(sensor_preset("tmf8820"), floor_plane(), lambda: looking_down(0.5), settings=FAST)
        await sensor.prepare()
        await sensor.next_frame(5)
        silenced = time.monotonic()
        sensor.inject_silence(1.0)  # far longer than the 0.1 s wait below, also on a loaded machine
        with pytest.raises(SensorSilent, match="sensor sim: no complete frame within 0.1 s"):
            await sensor.next_frame(0.1)
        after_silence = await sensor.next_frame(5)
        sensor.inject_link_loss(1.0)
        with pytest.raises(LinkLost, match="sensor sim: link down"):
            await sensor.next_frame(5)
        while sensor.counters()["link"] == "down":
            await asyncio.sleep(0.01)
        after_link = await sensor.next_frame(5)
        counters = sensor.counters()
        await sensor.release()
        return silenced, after_silence, after_link, counters

    silenced, after_silence, after_link, c = arun(main())
    assert after_silence.t_start >= silenced + 1.0 and after_link.hists.shape == (9, 128)
    assert c["silent_timeouts"] == 1 and c["faults_injected"] == 2 and c["frames"] == 3 and c["link"] == "up"


def test_scheduled_silence_delays_the_listed_frames_once(arun):
    async def main():
        sensor = SimSensor(sensor_preset("tmf8820"), floor_plane(), lambda: looking_down(0.5), settings=FAST,
                           silence_on_frames=(2,), silence_s=0.3)
        await sensor.prepare()
        try:
            first = [await sensor.next_frame(5) for _ in range(2)]  # frames 0 and 1: on time
            asked = time.monotonic()
            with pytest.raises(SensorSilent):  # frame 2 is due: silence instead
                await sensor.next_frame(0.1)
            during = sensor.counters()["silent"]
            late = await sensor.next_frame(5)  # frame 2, after the silence
            after = [await sensor.next_frame(5) for _ in range(2)]  # not silenced again (counted below)
            return first, asked, during, late, after, sensor.counters()
        finally:
            await sensor.release()

    first, asked, during, late, after, c = arun(main())
    assert during and not c["silent"]
    assert late.t_start >= asked + 0.3 and all(f.t_start < asked for f in first)
    assert c["frames"] == 5 and c["faults_injected"] == 1 and c["silent_timeouts"] == 1


@pytest.mark.parametrize("kw, words", [({"silence_on_frames": (-1,), "silence_s": 1.0}, "frame numbers >= 0"),
                                       ({"silence_on_frames": (3,)}, "needs a silence_s > 0"),
                                       ({"silence_s": -2.0}, "silence of -2.0 s is outside")])
def test_scheduled_silence_checks(kw, words):
    with pytest.raises(DeviceError, match=words):
        SimSensor(sensor_preset("tmf8820"), floor_plane(), lambda: np.eye(4), **kw)


def test_model_and_argument_checks(arun):
    sensor = SimSensor(sensor_preset("tmf8820"), floor_plane(), lambda: looking_down(0.5),
                       settings=SimSettings(rays_per_zone=256, cycles=1000))
    assert sensor.model.cycles == 1000  # the effective model, as captures must store it
    with pytest.raises(DeviceError, match="before prepare"):
        arun(sensor.next_frame(1))
    (f,) = arun(frames_of(sensor, 1))
    assert np.all(f.hists.sum(axis=1) <= 1000)
    with pytest.raises(DeviceError, match="frame time -1 s is outside"):
        SimSensor(sensor_preset("tmf8820"), floor_plane(), lambda: np.eye(4), frame_time_s=-1)
