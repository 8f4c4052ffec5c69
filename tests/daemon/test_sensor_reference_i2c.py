"""The I2C driver and its register fake against ams' reference drivers: the short-range switch and its check, the
result record (unsigned temperature, slot layout, 6-bit valid count), the error interrupt, and command statuses."""

from __future__ import annotations

import asyncio
import logging
import time

import numpy as np
import pytest
from smbus2 import i2c_msg

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.sensor.firmware import bootloader_frame
from spadscan.daemon.sensor.i2c_bus import I2CSensor, I2CTransport
from spadscan.daemon.sensor.i2c_records import RESULT_RECORD, parse_result_record, result_refusal, slot_target
from spadscan.daemon.sensor.sim_i2c import SimTMF8820Bus
from spadscan.daemon.sensor.tmf8820 import TMF8820
from spadscan.protocol.errors import DeviceError

from test_sensor_i2c import _run, image, reference_records, wake  # noqa: F401  (image: a fixture)

pytestmark = pytest.mark.usefixtures("no_leaked_threads_or_fds")


class StatusBus(SimTMF8820Bus):
    """The register fake, but command `cmd` answers `status` (a chip that disagrees with the references), and with
    `keep_range` command 0x6E is answered 0x00 while ACTIVE_RANGE stays where it was."""

    def __init__(self, cmd: int | None = None, status: int = 0x00, keep_range: bool = False, **kw):
        super().__init__(**kw)
        self.odd_cmd, self.odd_status, self.keep_range = cmd, status, keep_range

    def _command(self, cmd: int) -> None:
        if cmd == 0x6E and self.keep_range:
            self.commands.append(cmd)
            self.cmd_busy, self.cmd_stat = self.busy_polls, 0x00
            return
        super()._command(cmd)
        if cmd == self.odd_cmd:
            self.cmd_stat = self.odd_status


def _send(fake, cmd: int) -> int:
    """Command `cmd` written to CMD_STAT as a test host; its status once it no longer runs."""
    fake.write_byte_data(0x41, 0x08, cmd)
    while (status := fake.read_byte_data(0x41, 0x08)) >= 0x10:
        pass
    return status


def _started_fake(**kw) -> SimTMF8820Bus:
    """A fake whose application runs (RAMREMAP without an image check), as a test host left it."""
    fake = SimTMF8820Bus(startup_s=0.0, **kw)
    wake(fake)
    fake.i2c_rdwr(i2c_msg.write(0x41, b"\x08" + bootloader_frame(0x11)))
    assert fake.read_byte_data(0x41, 0x00) == 0x03
    return fake


# ---- 1. the short-range switch ------------------------------------------------------------------------------------
def test_the_fake_models_an_image_without_accuracy_modes():
    """ACTIVE_RANGE reads 0x00 ("no active range supported"), and command 0x6E is refused and changes nothing."""
    fake = _started_fake(accuracy_modes=False)
    assert fake.read_byte_data(0x41, 0x19) == 0x00
    assert _send(fake, 0x6E) == 0x06 and fake.read_byte_data(0x41, 0x19) == 0x00
    with_modes = _started_fake()
    assert with_modes.read_byte_data(0x41, 0x19) == 0x6F
    assert _send(with_modes, 0x6E) == 0x00 and with_modes.read_byte_data(0x41, 0x19) == 0x6E


def test_an_image_without_accuracy_modes_stops_the_start_before_anything_is_measured(arun, image):
    path, data = image
    fake = SimTMF8820Bus(image=data, accuracy_modes=False)
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake)
    with pytest.raises(DeviceError) as info:
        arun(_run(sensor, n_frames=1))
    message = str(info.value)
    assert "\n" not in message
    assert message == ("sensor i2c bus 1 addr 0x41: the sensor did not switch to short-range high-accuracy mode: "
                       "command 0x6e answered status 0x06 (unknown command) and ACTIVE_RANGE 0x19 reads 0x00 (an "
                       "application image without accuracy modes); the tmf8820 sensor model describes short-range "
                       "histograms only, so nothing is measured: set firmware = PATH to an ams TMF8820 application "
                       "image with accuracy modes (short_range_accuracy), then power-cycle the sensor")
    assert 0x10 not in fake.commands and fake.produced == []  # never told to measure: no frame can be stored


def test_a_switch_the_chip_acknowledges_but_does_not_make_is_caught_by_reading_active_range_again(arun, image):
    """ams' Linux driver reads ACTIVE_RANGE again after 0x6E and fails unless it reads 0x6E."""
    path, data = image
    fake = StatusBus(image=data, keep_range=True)
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake)
    with pytest.raises(DeviceError, match=r"command 0x6e answered status 0x00 \(ok\) and ACTIVE_RANGE 0x19 reads "
                                          r"0x6f \(still long range\)"):
        arun(_run(sensor, n_frames=1))
    assert 0x10 not in fake.commands and fake.produced == []


def test_the_refused_switch_reaches_the_user_as_the_rig_start_error(arun, image):
    """The daemon starts its devices in a DeviceSession: its one-line "rig did not start" error (what `spadscan
    daemon` prints) carries the sensor's reason."""
    path, data = image
    fake = SimTMF8820Bus(image=data, accuracy_modes=False)

    async def main():
        with pytest.raises(DeviceError) as info:
            async with DeviceSession([I2CSensor(1, firmware=path, smbus_factory=fake)]):
                pass
        return str(info.value)

    message = arun(main())
    assert message.startswith("rig did not start: sensor i2c bus 1 addr 0x41: the sensor did not switch to "
                              "short-range high-accuracy mode: ") and "\n" not in message
    assert "reads 0x00 (an application image without accuracy modes)" in message
    assert fake.produced == []


# ---- 2. the temperature byte ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("byte", [0, 25, 127, 128, 200, 255])
def test_the_temperature_is_an_unsigned_byte(byte):
    records = reference_records(np.zeros((10, 128), int), 3, byte, 1, [0] * 36, [0] * 36)
    pkt = parse_result_record(records[-1][1], 0.0)
    assert pkt is not None and pkt.temperature_c == float(byte)


def test_the_fake_reports_a_die_temperature_a_chip_reports(arun, image):
    path, data = image
    fake = SimTMF8820Bus(image=data, seed=3)
    frames = arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=6))
    temperatures = [result["temperature_c"] for _, result in fake.produced]
    assert all(20 <= t <= 60 for t in temperatures)
    assert [f.temperature_c for f in frames] == [float(t) for t in temperatures[:6]]


# ---- 3. the result slots and the valid count ------------------------------------------------------------------------
def test_result_slots_are_targets_of_channels_in_sub_captures():
    """ams' Linux driver: channel (k % 9) + 1, sub-capture (k // 9) % 2; its Python driver: object1 = slots 0-17,
    object2 = slots 18-35."""
    assert [slot_target(k) for k in (0, 8, 9, 17, 18, 26, 27, 35)] == [
        (1, 0, 1), (9, 0, 1), (1, 1, 1), (9, 1, 1), (1, 0, 2), (9, 0, 2), (1, 1, 2), (9, 1, 2)]
    with pytest.raises(ValueError):
        slot_target(36)


def test_the_fake_fills_the_slots_one_spad_map_fills(arun, image):
    path, data = image
    fake = SimTMF8820Bus(image=data, seed=5)
    frames = arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=8))
    seconds = 0
    for frame, (_, result) in zip(frames, fake.produced):
        conf, dist = result["confidences"], result["distances_mm"]
        assert conf[9:18] == [0] * 9 and conf[27:36] == [0] * 9  # sub-capture 1: no time multiplexing
        assert dist[9:18] == [0] * 9 and dist[27:36] == [0] * 9
        for zone in range(9):
            if conf[zone] == 0:  # no first target: no target at all
                assert dist[zone] == 0 and conf[18 + zone] == 0
            if conf[18 + zone]:
                assert dist[18 + zone] > dist[zone] > 0  # the second target lies behind the first
                seconds += 1
        assert frame.extra["n_valid"] == sum(1 for c in conf if c) == result["n_valid"]
        assert frame.confidences == conf and frame.depths_mm == [float(d) for d in dist]
    assert seconds > 0 and any(c == 0 for _, r in fake.produced for c in r["confidences"][:9])


def test_the_valid_count_is_the_low_six_bits_of_its_byte():
    """The register map's NUMBER_VALID_RESULTS is a 6-bit field (mask 0x3F): bits above it are no count."""
    confidences = [50] * 9 + [0] * 27
    bit, result = reference_records(np.zeros((10, 128), int), 3, 30, 1, list(range(1, 37)), confidences)[-1]
    flagged = result[:6] + bytes([0x40 | 9]) + result[7:]
    assert result_refusal(flagged) == ""
    pkt = parse_result_record(flagged, 0.0)
    assert pkt is not None and pkt.n_valid == 9
    too_many = result[:6] + bytes([37]) + result[7:]
    assert result_refusal(too_many) == "37 valid results (count byte 0x25), more than 36"
    assert len(flagged) == RESULT_RECORD


# ---- 4. the error interrupt -----------------------------------------------------------------------------------------
async def _until(predicate, what: str, limit_s: float = 20.0):
    deadline = time.monotonic() + limit_s
    while not predicate():
        assert time.monotonic() < deadline, f"{what} never happened"
        await asyncio.sleep(0.01)


def test_an_application_that_stops_with_its_error_interrupt_is_noticed_at_the_next_poll(arun, image):
    """The chip raises INT_STATUS bit 0x40 as it stops (CMD_STAT 0x03): the driver sees it at its next poll, long
    before its silence watchdog (60 s here) would, clears it and restarts the sensor, naming the registers."""
    path, data = image
    fake = SimTMF8820Bus(image=data, frame_interval_s=0.02)
    sensor = TMF8820(I2CTransport(1, firmware=path, smbus_factory=fake, watchdog_s=60.0))

    async def during(sensor):
        fake.stop_measuring(cmd_stat=0x03, app_status=0x04)
        await _until(lambda: sensor.counters()["reconnects"] >= 1, "a restart after the error interrupt")
        return [await sensor.next_frame(10)]

    arun(_run(sensor, n_frames=1, during=during))
    c = sensor.counters()
    assert c["last_link_error"] == (
        "sensor stopped measuring (CMD_STAT 0x03 (application error, stopped), APPLICATION_STATUS 0x04, "
        "MEASURE_STATUS 0x00, ALGORITHM_STATUS 0x00, FACTORY_CALIBRATION_STATUS 0x00, error interrupt: INT_STATUS "
        "bit 0x40)")
    assert c["boots"] == 2 and fake.violations == [] and not fake.error_irq  # cleared, and measuring again


def test_an_error_interrupt_while_the_application_measures_on_is_counted_and_reading_goes_on(arun, image, caplog):
    path, data = image
    fake = SimTMF8820Bus(image=data, frame_interval_s=0.02)
    sensor = TMF8820(I2CTransport(1, firmware=path, smbus_factory=fake, watchdog_s=60.0))

    async def during(sensor):
        fake.set_status(app_status=0x05, error_interrupt=True)  # a warning status: the application measures on
        await _until(lambda: not fake.error_irq, "the driver clearing the error interrupt")
        return [await sensor.next_frame(10) for _ in range(2)]

    with caplog.at_level(logging.WARNING, logger="spadscan.daemon"):
        frames = arun(_run(sensor, n_frames=1, during=during))
    c = sensor.counters()
    assert len(frames) == 3 and c["error_interrupts"] == 1 and c["link_drops"] == 0
    assert c["last_error_interrupt"] == ("APPLICATION_STATUS 0x05, MEASURE_STATUS 0x00, ALGORITHM_STATUS 0x00, "
                                         "FACTORY_CALIBRATION_STATUS 0x00")
    assert "raised its error interrupt (INT_STATUS bit 0x40: APPLICATION_STATUS 0x05" in caplog.text


def test_cmd_stat_is_checked_before_each_record_is_read(arun, image):
    """ams' Linux driver checks CMD_STAT before it reads a message: a record still flagged after the application
    reported an error is not read, and the link is restarted at once (not after the watchdog's 60 s)."""
    path, data = image
    fake = SimTMF8820Bus(image=data, frame_interval_s=0.02)
    sensor = TMF8820(I2CTransport(1, firmware=path, smbus_factory=fake, watchdog_s=60.0))

    async def during(sensor):
        fake.set_status(cmd_stat=0x02)  # an error status while records still come, without the error interrupt
        await _until(lambda: sensor.counters()["link_drops"] >= 1, "the driver refusing to read on")
        await _until(lambda: sensor.counters()["reconnects"] >= 1, "the restart")
        return [await sensor.next_frame(10)]

    arun(_run(sensor, n_frames=1, during=during))
    assert "CMD_STAT 0x02 (configuration not accepted), APPLICATION_STATUS 0x00, before a record read" in (
        sensor.counters()["last_link_error"])


# ---- 5. command statuses --------------------------------------------------------------------------------------------
def test_the_fake_answers_each_command_as_ams_python_driver_expects():
    fake = _started_fake()
    assert [_send(fake, cmd) for cmd in (0x6E, 0x16, 0x15, 0x10, 0xFF)] == [0x00, 0x00, 0x00, 0x01, 0x00]


@pytest.mark.parametrize("cmd, message", [
    (0x16, r"command 0x16 \(load common config\) answered status 0x01 \(accepted\), expected 0x00 \(ok\)"),
    (0x15, r"command 0x15 \(write config\) answered status 0x01 \(accepted\), expected 0x00 \(ok\)"),
    (0x6E, r"did not switch to short-range high-accuracy mode: command 0x6e answered status 0x01 \(accepted\) and "
           r"ACTIVE_RANGE 0x19 reads 0x6e \(short range, but the command did not answer 0x00\)"),
])
def test_accepted_is_an_answer_only_measure_may_give(arun, image, cmd, message):
    path, data = image
    fake = StatusBus(cmd=cmd, status=0x01, image=data)
    with pytest.raises(DeviceError, match=message):
        arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=1))
    assert 0x10 not in fake.commands


def test_a_stop_answered_accepted_is_refused(image):
    path, data = image
    fake = StatusBus(cmd=0xFF, status=0x01, image=data)
    transport = I2CTransport(1, firmware=path, smbus_factory=fake)
    transport.open()
    try:
        transport.start()
        with pytest.raises(DeviceError, match=r"command 0xff \(stop\) answered status 0x01 \(accepted\), expected "
                                              r"0x00 \(ok\)"):
            transport.restart()
    finally:
        transport.close()
