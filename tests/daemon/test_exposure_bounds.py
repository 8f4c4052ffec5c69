"""A frame's t_start is a lower bound on when its exposure began (`Frame`): the runner drops frames that began
before the arm settled. The fakes record when each measurement was really exposed (cyclic measurement, one-frame
buffer); the I2C sensor restarts its measurement when the arm has settled (`begin_exposure`), the bridge cannot."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from spadscan.daemon.backends.sensor_serial import SerialSensorSettings
from spadscan.daemon.sensor.i2c_bus import I2CSensor
from spadscan.daemon.sensor.serial_bridge import SerialSensor
from spadscan.daemon.sensor.sim_bridge import SimBridge
from spadscan.daemon.sensor.sim_i2c import SimTMF8820Bus
from spadscan.protocol.sensor_presets import sensor_preset

from test_sensor_i2c import image  # noqa: F401  (a fixture: the stand-in application image)

pytestmark = pytest.mark.usefixtures("no_leaked_threads_or_fds")

CMD_MEASURE, CMD_STOP = 0x10, 0xFF


class TimedBus(SimTMF8820Bus):
    """The register fake with the time each transfer takes on a bus of `khz` (9 bits a byte, the address included),
    so that reading a frame out overlaps the next measurement as on the rig."""

    def __init__(self, khz: float, **kw):
        super().__init__(**kw)
        self.byte_s = 9 / (khz * 1e3)

    def i2c_rdwr(self, *msgs):
        time.sleep(sum(m.len + 1 for m in msgs) * self.byte_s)
        return super().i2c_rdwr(*msgs)


def exposure_of_i2c(fake: SimTMF8820Bus, frame) -> tuple[float, float]:
    """The fake's (begin, end) of the measurement a frame carries (its result's system ticks are random)."""
    (n,) = [k for k, (_, res) in enumerate(fake.produced) if res["systick"] == frame.extra["systick"]]
    assert np.array_equal(fake.produced[n][0][1:], frame.hists)
    return fake.exposures[n]


def i2c_sensor(image, fake, period_ms):
    return I2CSensor(1, firmware=image[0], smbus_factory=fake, period_ms=period_ms, timeout_s=5.0)


# ---- I2C ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("interval_s", [0.1, 0.03], ids=["period-as-configured", "chip-faster-than-the-readout"])
def test_every_i2c_frame_starts_no_later_than_its_exposure(arun, image, interval_s):
    """At 400 kHz a frame takes ~0.1 s to read out, while the chip exposes the next: t_start must count back to
    that exposure (a buffered measurement may even have finished before the previous frame's result arrived)."""
    fake = TimedBus(400, image=image[1], frame_interval_s=interval_s, handover_s=0.0005)
    sensor = i2c_sensor(image, fake, round(interval_s * 1000))

    async def main():
        await sensor.connect()
        try:
            await sensor.prepare()
            return [await sensor.next_frame(10) for _ in range(8)]
        finally:
            await sensor.release()
            await sensor.close()

    frames = arun(main())
    for f in frames:
        begin, _ = exposure_of_i2c(fake, f)
        assert f.t_start <= begin, f"t_start {f.t_start - begin:+.3f} s after the exposure began"
    assert not fake.violations


def test_after_begin_exposure_every_i2c_frame_was_exposed_after_it(arun, image):
    """Frames measured while the arm moved wait in the queue; begin_exposure stops and restarts the measurement (0xFF,
    then 0x10, as ams' drivers do), discards them, and every later frame was exposed after the call."""
    fake = TimedBus(400, image=image[1], frame_interval_s=0.05, handover_s=0.0005)
    sensor = i2c_sensor(image, fake, 50)

    async def main():
        await sensor.connect()
        try:
            await sensor.prepare()
            await sensor.next_frame(10)
            while sensor.counters()["queued"] < 2:  # frames of the move pile up
                await asyncio.sleep(0.01)
            settled = time.monotonic()
            restarted_at = await sensor.begin_exposure()
            frames = [await sensor.next_frame(10) for _ in range(3)]
            return settled, restarted_at, frames, sensor.counters()
        finally:
            await sensor.release()
            await sensor.close()

    settled, restarted_at, frames, c = arun(main())
    assert restarted_at is not None and restarted_at >= settled
    for f in frames:
        begin, _ = exposure_of_i2c(fake, f)
        assert restarted_at <= f.t_start <= begin  # kept by a runner that settled at `settled`, and honest
    assert c["restarts"] == 1 and c["frames_discarded_at_restart"] >= 2
    assert fake.commands[-3:] == [CMD_STOP, CMD_MEASURE, CMD_STOP] and not fake.violations  # restart, release


# ---- the serial bridge -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("period_s, line_s", [(0.1, 0.005), (0.2, 0.002)],
                         ids=["bridge-slower-than-the-chip", "bridge-faster-than-the-chip"])
def test_every_bridge_frame_starts_no_later_than_its_exposure(arun, period_s, line_s):
    """The bridge cannot restart the measurement: its frames count back two periods and the link's lag from the line
    before them. Slower than the chip it prints measurements that finished before the previous result line; faster,
    it prints ones exposed while it printed the previous frame."""
    rng = np.random.default_rng(3)

    async def main():
        with SimBridge() as bridge:
            sensor = SerialSensor(bridge.port, period_ms=period_s * 1000)
            await sensor.connect()
            try:
                await sensor.prepare()
                assert await sensor.begin_exposure() is None  # it measures on its own
                bridge.start_measuring(lambda: rng.integers(0, 1 << 24, (10, 128)), period_s, line_s=line_s)
                frames = [await sensor.next_frame(10) for _ in range(8)]
                bridge.stop_stream()
                return frames, dict(bridge.exposures)
            finally:
                await sensor.release()
                await sensor.close()

    frames, exposures = arun(main())
    for f in frames:
        begin, _ = exposures[f.extra["systick"]]
        assert f.t_start <= begin, f"t_start {f.t_start - begin:+.3f} s after the exposure began"


def test_a_failed_restart_is_a_dropped_link_and_later_frames_follow_the_reconnect(arun, image):
    """The chip lost power while the arm moved: its transfers are not acknowledged (a read's or the restart's), the
    link is down, begin_exposure says so (None) and the sensor boots again, which starts the measurement afresh: no
    later frame began before it."""
    fake = SimTMF8820Bus(image=image[1], frame_interval_s=0.02)
    sensor = i2c_sensor(image, fake, 20)

    async def main():
        await sensor.connect()
        try:
            await sensor.prepare()
            await sensor.next_frame(10)
            fake.power_cycle()
            settled = time.monotonic()
            restarted_at = await sensor.begin_exposure()
            frame = await sensor.next_frame(10)
            return settled, restarted_at, frame, sensor.counters()
        finally:
            await sensor.release()
            await sensor.close()

    settled, restarted_at, frame, c = arun(main())
    assert restarted_at is None and c["restarts"] == 0 and c["reconnects"] == 1 and c["downloads"] == 2
    begin, _ = exposure_of_i2c(fake, frame)
    assert settled <= frame.t_start <= begin


def test_the_bridge_period_key_reaches_the_sensor():
    settings = SerialSensorSettings(port="/dev/ttyACM0", bridge_period_ms=500)
    sensor = settings.build(None, sensor_preset("tmf8820"), None, np.eye(4), "[sensor]")
    assert sensor.transport.period_s == 0.5 and sensor._assembler.lookback_s() >= 1.0
