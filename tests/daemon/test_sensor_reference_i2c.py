"""The I2C driver and its register fake against ams' reference drivers: the short-range switch and its check, the
result record (unsigned temperature, slot layout, 6-bit valid count), the error interrupt and the CMD_STAT checks
while measuring (once per frame; a command echo that never settles), command statuses, a warm start after another
tool (POWER_CFG, a TMF8828's 8x8 mode), the power-up state (PON set), the "any" interrupt bit, and the TID."""

from __future__ import annotations

import asyncio
import collections
import ctypes
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
from spadscan.daemon.sensor.transport import LinkDown, ResultPacket
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


def test_an_error_status_while_records_still_come_restarts_the_link_at_the_next_frame(arun, image):
    """ams' Linux driver checks CMD_STAT before it reads a message; the driver checks it before each frame's first
    record: an error status without the error interrupt restarts the link then (not after the watchdog's 60 s)."""
    path, data = image
    fake = SimTMF8820Bus(image=data, frame_interval_s=0.02)
    sensor = TMF8820(I2CTransport(1, firmware=path, smbus_factory=fake, watchdog_s=60.0))

    async def during(sensor):
        fake.set_status(cmd_stat=0x02)  # an error status while records still come, without the error interrupt
        await _until(lambda: sensor.counters()["link_drops"] >= 1, "the driver refusing to read on")
        await _until(lambda: sensor.counters()["reconnects"] >= 1, "the restart")
        return [await sensor.next_frame(10)]

    arun(_run(sensor, n_frames=1, during=during))
    assert sensor.counters()["last_link_error"] == (
        "sensor stopped measuring (CMD_STAT 0x02 (configuration not accepted), APPLICATION_STATUS 0x00, before a "
        "frame's first record)")


class ChipReplay:
    """Serves records as the chip hands them over (INT_STATUS shows the waiting record's bit, 0x20 holds its bytes,
    writing the bit back hands the next one over), with CMD_STAT reading `cmd_stat` (0x01 while measuring; a command
    still running is echoed, >= 0x10, ams' register map) and, with `error`, the error interrupt (INT_STATUS bit 0x40)
    raised with the first record until the host clears it. Counts the reads of each register in `reads`."""

    def __init__(self, records, cmd_stat: int = 0x01, error: bool = False):
        self.records, self.cmd_stat, self.error = list(records), cmd_stat, error
        self.reads: collections.Counter = collections.Counter()

    def read_byte_data(self, addr, register, force=None):
        self.reads[register] += 1
        if register == 0x08:
            return self.cmd_stat
        if 0x04 <= register <= 0x07:
            return 0x00  # the status registers
        assert register == 0xE1
        return (self.records[0][0] if self.records else 0) | (0x40 if self.error else 0)

    def write_byte_data(self, addr, register, value, force=None):
        assert register == 0xE1
        if value & 0x40:
            self.error = False
        if self.records and value & self.records[0][0]:
            self.records.pop(0)

    def i2c_rdwr(self, write, read):
        assert list(write) == [0x20]
        ctypes.memmove(read.buf, self.records[0][1][:read.len].ljust(read.len, b"\0"), read.len)

    def close(self):
        pass


def _frames(n: int) -> list:
    """n frames' records laid out as ams' drivers decode them (`reference_records`)."""
    rng = np.random.default_rng(21)
    out = []
    for k in range(n):
        out += reference_records(rng.integers(0, 1 << 24, (10, 128)), k, 30, k, list(range(36)), [9] * 9 + [0] * 27)
    return out


def _read_all(chip: ChipReplay, n_reads: int, **kw) -> tuple[list, dict]:
    """Read `n_reads` packets from `chip` through an I2CTransport; (packets, its counters)."""
    transport = I2CTransport(1, smbus_factory=lambda bus: chip, **kw)
    transport.open()
    try:
        return [transport.read_packet(0.0) for _ in range(n_reads)], transport.counters()
    finally:
        transport.close()


def test_cmd_stat_is_read_once_per_frame_not_before_every_record():
    """31 records a frame: one CMD_STAT read per record cost ~3 % of the frame rate at 400 kHz."""
    chip = ChipReplay(_frames(3))
    packets, c = _read_all(chip, 93)
    assert sum(isinstance(p, ResultPacket) for p in packets) == 3 and c["bad_records"] == 0
    assert chip.reads[0x08] == 3


def test_an_error_interrupt_with_a_record_reads_cmd_stat_once():
    """The error interrupt's check reads CMD_STAT; the record read with it at the same poll needs no second read."""
    chip = ChipReplay(_frames(1), error=True)
    packets, c = _read_all(chip, 31)
    assert packets[0].index == 0 and c["error_interrupts"] == 1 and not chip.error
    assert chip.reads[0x08] == 1


@pytest.mark.parametrize("spoil", ["refused", "missing"])
def test_a_refused_or_missing_record_has_cmd_stat_read_before_the_next_one(spoil):
    records = _frames(2)
    if spoil == "refused":
        bit, rec = records[5]
        records[5] = (bit, b"\x7f" + rec[1:])  # another RID: refused
    else:
        del records[5]  # sub-packet 5 never came
    chip = ChipReplay(records)
    packets, c = _read_all(chip, len(records))
    assert c["bad_records"] == (spoil == "refused")
    assert chip.reads[0x08] == 2 + 1  # each frame's, and one before the record after the spoiled one


@pytest.mark.parametrize("echo, running", [(0x10, "measure"), (0xFF, "stop"), (0x43, "command 0x43")])
def test_a_cmd_stat_that_keeps_echoing_a_command_is_a_dropped_link(echo, running):
    """An application hung in a command echoes it in CMD_STAT for good: the device must boot it again (LinkDown),
    not give up on the sensor (a plain DeviceError stops its reader for good)."""
    chip = ChipReplay(_frames(1), cmd_stat=echo)
    with pytest.raises(LinkDown) as info:
        _read_all(chip, 1, timeout_s=0.05)
    assert str(info.value) == (f"sensor stopped measuring (CMD_STAT stuck at {echo:#04x} ({running} still running) for "
                               f"0.05 s, APPLICATION_STATUS 0x00, before a frame's first record)")


def test_an_application_hung_in_a_command_is_booted_again_not_given_up(arun, image):
    """The application hangs measuring (CMD_STAT stuck at 0x10, no record): the silence watchdog finds the echo
    that never settles and drops the link; the device keeps trying (the hung chip takes no stop) until the sensor is
    power-cycled, and frames flow again."""
    path, data = image
    fake = SimTMF8820Bus(image=data, frame_interval_s=0.02)
    sensor = TMF8820(I2CTransport(1, firmware=path, smbus_factory=fake, watchdog_s=0.3, timeout_s=0.2),
                     link_grace_s=60.0)

    async def during(sensor):
        fake.hang(0x10)
        await _until(lambda: sensor.counters()["reconnect_failures"] >= 1, "a failed restart of the hung chip")
        fake.power_cycle()
        await _until(lambda: sensor.counters()["reconnects"] >= 1, "the restart after the power cycle")
        return [await sensor.next_frame(10)]

    frames = arun(_run(sensor, n_frames=1, during=during))
    c = sensor.counters()
    assert len(frames) == 2 and c["link_drops"] == 1 and c["downloads"] == 2
    assert fake.commands.count(0x10) == 2  # measuring again after the power cycle


# ---- 5. command statuses --------------------------------------------------------------------------------------------
def test_the_fake_answers_each_command_as_ams_python_driver_expects():
    fake = _started_fake()
    assert [_send(fake, cmd) for cmd in (0x6E, 0x16, 0x15, 0x10, 0xFF)] == [0x00, 0x00, 0x00, 0x01, 0x00]


def _driver_notes_over_a_power_loss(arun, fake, path, caplog) -> list[str]:
    """The warnings where a command's status differs from what ams' Python driver expects, over a start, a power
    loss and the start after it (a frame each)."""
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake)

    async def during(sensor):
        fake.power_cycle()
        await _until(lambda: sensor.counters()["reconnects"] >= 1, "the start after the power loss")
        return [await sensor.next_frame(10)]

    with caplog.at_level(logging.WARNING, logger="spadscan.daemon"):
        frames = arun(_run(sensor, n_frames=1, during=during))
    assert len(frames) == 2 and sensor.counters()["boots"] == 2
    return [r.getMessage() for r in caplog.records if "Python driver expects" in r.getMessage()]


@pytest.mark.parametrize("cmd", [0x16, 0x15])
def test_a_config_command_answered_accepted_is_taken_and_said_once(arun, image, caplog, cmd):
    """ams' Linux driver takes 0x00 or 0x01 after any command (its Python driver expects 0x00 here): the start goes
    on, and the difference is logged once, not at every start (here again after a power loss)."""
    path, data = image
    fake = StatusBus(cmd=cmd, status=0x01, image=data, frame_interval_s=0.02)
    said = _driver_notes_over_a_power_loss(arun, fake, path, caplog)
    name = {0x16: "load common config", 0x15: "write config"}[cmd]
    assert said == [f"i2c bus 1 addr 0x41: command {cmd:#04x} ({name}) answered status 0x01 (accepted) where ams' "
                    f"Python driver expects 0x00 (ok); taken, as ams' Linux driver takes 0x00 or 0x01 after any "
                    f"command (said once)"]


@pytest.mark.parametrize("status", [0x01, 0x06])
def test_the_short_range_switch_is_decided_by_active_range_whatever_its_status(arun, image, caplog, status):
    """ACTIVE_RANGE reads 0x6E after the switch: that is the mode the model needs, whatever the command answered."""
    path, data = image
    fake = StatusBus(cmd=0x6E, status=status, image=data)
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake)
    with caplog.at_level(logging.WARNING, logger="spadscan.daemon"):
        frames = arun(_run(sensor, n_frames=1))
    assert len(frames) == 1 and fake.active_range == 0x6E and sensor.counters()["active_range"] == "short range"
    assert f"command 0x6e (short-range mode) answered status {status:#04x}" in caplog.text
    assert "ACTIVE_RANGE reads 0x6e (short range), which decides" in caplog.text
    assert "firmware = PATH" not in caplog.text


class StatusesBus(SimTMF8820Bus):
    """The register fake, but each command in `statuses` answers the status given there."""

    def __init__(self, statuses: dict[int, int], **kw):
        super().__init__(**kw)
        self.statuses = statuses

    def _command(self, cmd: int) -> None:
        super()._command(cmd)
        if cmd in self.statuses:
            self.cmd_stat = self.statuses[cmd]


def test_the_short_range_note_and_a_config_commands_note_are_each_said(arun, image, caplog):
    """Both the short-range switch and a config command answer 0x01: each is logged once (before, the first note
    hid the other for the transport's life)."""
    path, data = image
    fake = StatusesBus({0x6E: 0x01, 0x15: 0x01}, image=data, frame_interval_s=0.02)
    said = _driver_notes_over_a_power_loss(arun, fake, path, caplog)
    assert len(said) == 2, said
    assert said[0].startswith("i2c bus 1 addr 0x41: command 0x6e (short-range mode) answered status 0x01"), said
    assert said[1].startswith("i2c bus 1 addr 0x41: command 0x15 (write config) answered status 0x01"), said


def test_a_command_status_that_is_an_error_still_fails_the_start(arun, image):
    path, data = image
    fake = StatusBus(cmd=0x16, status=0x02, image=data)
    with pytest.raises(DeviceError, match=r"command 0x16 \(load common config\) answered status 0x02 "
                                          r"\(configuration not accepted\), expected 0x00 \(ok\) or 0x01 "
                                          r"\(accepted\)$"):
        arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=1))
    assert 0x10 not in fake.commands


def test_a_chip_that_answers_stop_with_accepted_restarts_and_reconnects(arun, image):
    """A stop answered 0x01 (ams' Linux driver takes it) no longer fails the restart at each settle, nor the
    reconnect's start that sends stop again (which, refused, failed for good)."""
    path, data = image
    fake = StatusBus(cmd=0xFF, status=0x01, image=data, frame_interval_s=0.02)
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake)

    async def during(sensor):
        t = await sensor.begin_exposure()
        frame = await sensor.next_frame(10)
        assert t is not None and frame.t_start >= t
        return [frame]

    frames = arun(_run(sensor, n_frames=1, during=during))
    c = sensor.counters()
    assert len(frames) == 2 and c["restarts"] == 1 and c["link_drops"] == 0
    again = I2CSensor(1, firmware=path, smbus_factory=fake)  # the application still runs: start sends stop first
    assert len(arun(_run(again, n_frames=1))) == 1 and again.counters()["downloads"] == 0


# ---- 6. a warm start after another tool: POWER_CFG and a TMF8828's 8x8 mode ------------------------------------------
def _another_tool_configures(fake, power_cfg: int) -> None:
    """As a test host: load the common config page, write POWER_CFG 0x33, write the page back."""
    assert _send(fake, 0x16) == 0x00
    fake.write_byte_data(0x41, 0x33, power_cfg)
    assert _send(fake, 0x15) == 0x00


def test_a_start_after_another_tool_clears_the_power_fields_ams_names(arun, image):
    """The application keeps POWER_CFG while it stays powered: timed standby between measurements (0x80) and an
    oscillator retrim (0x08) another tool set are cleared (their reset values, ams' register map); a bit the map does
    not name (0x02 here) is kept as it was."""
    path, data = image
    fake = SimTMF8820Bus(image=data)
    arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=1))
    _another_tool_configures(fake, 0x80 | 0x08 | 0x02)
    assert fake.config["power_cfg"] == 0x8A
    frames = arun(_run(I2CSensor(1, smbus_factory=fake), n_frames=1))
    assert len(frames) == 1 and fake.violations == []
    assert fake.config["power_cfg"] == 0x02


def test_the_fake_models_a_tmf8828s_8x8_mode():
    """TMF8828_MODE 0x10 reads 0x00 (3x3, the reset value) or 0x08 (8x8); 0x6C and 0x65 switch, and a switch resets
    the configuration (8x8 mode: SPAD map 15). An image without 8x8 measurements refuses both."""
    fake = _started_fake(tmf8828=True)
    assert fake.read_byte_data(0x41, 0x10) == 0x00
    assert _send(fake, 0x6C) == 0x00 and fake.read_byte_data(0x41, 0x10) == 0x08 and fake.config["spad_map"] == 15
    assert _send(fake, 0x65) == 0x00 and fake.read_byte_data(0x41, 0x10) == 0x00 and fake.config["spad_map"] == 1
    tmf8820 = _started_fake()
    assert _send(tmf8820, 0x6C) == 0x06 and tmf8820.read_byte_data(0x41, 0x10) == 0x00


def test_a_start_after_another_tool_left_a_tmf8828_in_8x8_mode_switches_it_to_3x3(arun, image):
    path, data = image
    fake = SimTMF8820Bus(image=data, tmf8828=True)
    arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=1))
    assert _send(fake, 0x6C) == 0x00  # another tool; the application still runs, in 8x8 mode
    fake.commands.clear()
    sensor = I2CSensor(1, smbus_factory=fake)
    frames = arun(_run(sensor, n_frames=1))
    assert len(frames) == 1 and fake.violations == [] and sensor.counters()["downloads"] == 0
    assert fake.read_byte_data(0x41, 0x10) == 0x00 and fake.config["spad_map"] == 1
    # stop, the switch before the configuration (ACTIVE_RANGE still reads 0x6E: no 0x6E), measure, stop on release
    assert fake.commands == [0xFF, 0x65, 0x16, 0x15, 0x10, 0xFF]


class StuckIn8x8Bus(SimTMF8820Bus):
    """A TMF8828 that answers 0x65 but stays in 8x8 mode."""

    def _command(self, cmd: int) -> None:
        if cmd == 0x65:
            self.commands.append(cmd)
            self.cmd_busy, self.cmd_stat = self.busy_polls, 0x00
            return
        super()._command(cmd)


def test_a_tmf8828_that_stays_in_8x8_mode_fails_the_start_before_anything_is_measured(arun, image):
    path, data = image
    fake = StuckIn8x8Bus(image=data, tmf8828=True)
    arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=1))
    assert _send(fake, 0x6C) == 0x00
    with pytest.raises(DeviceError, match=r"the sensor did not leave 8x8 mode: TMF8828_MODE 0x10 read 0x08, and "
                                          r"0x08 after command 0x65 \(3x3 mode\)"):
        arun(_run(I2CSensor(1, smbus_factory=fake), n_frames=1))
    assert 0x10 not in fake.commands[fake.commands.index(0x65):]  # nothing measured after the failed switch


# ---- 7. power-up state, the "any" interrupt bit, the TID -------------------------------------------------------------
def test_the_fake_powers_up_with_pon_set_and_boots_its_bootloader_by_itself():
    """ENABLE's PON resets to 1 (ams' register map; ams' Arduino driver's TMF8828_ENABLE__pon__RESET): after power
    comes the chip answers nothing while its CPU starts, then reads PON and cpu_ready (0x41) in its bootloader, with no
    PON written by the host."""
    fake = SimTMF8820Bus(startup_s=0.01)
    fake.power_cycle()
    deadline = time.monotonic() + 5.0
    while True:
        try:
            enable = fake.read_byte_data(0x41, 0xE0)
        except OSError:
            enable = None  # the CPU starts: nothing is acknowledged
        if enable is not None and enable & 0x40:
            break
        assert enable is None or enable & 0x01, f"ENABLE {enable:#04x}: PON cleared after power-up"
        assert time.monotonic() < deadline, f"cpu_ready never came (ENABLE {enable})"
    assert enable == 0x41 and fake.read_byte_data(0x41, 0x00) == 0x80 and fake.nacked_while_starting > 0


def test_a_record_read_leaves_no_interrupt_flagged_the_any_bit_included(image):
    """INT_STATUS bit 0x01 ("any interrupt has occurred") goes up with each record; ams' Arduino driver clears it with
    each record (its Linux driver writes back every bit it read). Left set, it holds the INT pin low for good where
    another tool enabled it (INT_ENAB bit 0x01, which the read-modify-write keeps). The measure command's "command
    done" (0x20) stays set, as ams' Python driver leaves it: not enabled, it does not hold the pin."""
    path, data = image
    fake = SimTMF8820Bus(image=data, handover_s=0.5)  # the next record comes long after the checks below
    fake.int_enab = 0x01
    transport = I2CTransport(1, firmware=path, smbus_factory=fake)
    transport.open()
    try:
        transport.start()
        assert fake.int_pin_low()
        assert transport.read_packet(5.0).index == 0
        assert fake.read_byte_data(0x41, 0xE1) == 0x20 and not fake.int_pin_low()
    finally:
        transport.stop()
        transport.close()
    assert fake.violations == []


def test_an_error_interrupt_cleared_leaves_no_interrupt_flagged_the_any_bit_included(image):
    """The error interrupt (INT_STATUS bit 0x40) raises the "any" bit 0x01 with it: clearing the error clears that bit
    too, so that the INT pin does not stay low (INT_ENAB bit 0x01 enabled by another tool) until a record comes."""
    path, data = image
    fake = SimTMF8820Bus(image=data, handover_s=5.0)  # no record comes during the checks below
    fake.int_enab = 0x01
    transport = I2CTransport(1, firmware=path, smbus_factory=fake)
    transport.open()
    try:
        transport.start()
        assert transport.read_packet(5.0).index == 0  # the first record read: nothing flagged until the next one
        fake.set_status(app_status=0x05, error_interrupt=True)  # a warning: the application measures on
        assert fake.read_byte_data(0x41, 0xE1) == 0x61 and fake.int_pin_low()  # 0x20: the measure command's done
        assert transport.read_packet(0.0) is None  # the poll that sees the error interrupt and clears it
        assert transport.counters()["error_interrupts"] == 1
        assert fake.read_byte_data(0x41, 0xE1) == 0x20 and not fake.int_pin_low()
    finally:
        transport.stop()
        transport.close()
    assert fake.violations == []


def test_the_fake_raises_command_done_when_a_command_is_handled():
    """INT_STATUS bit 0x20 (ams' TMF8X2X_APP_I2C_CMD_DONE_IRQ_MASK: "a received I2C command has been handled
    (successfully or failed)"), with bit 0x01: up once CMD_STAT no longer echoes the command, whatever its status, kept
    until the host writes 1 to it; enabled in INT_ENAB it pulls the INT pin. A command the application hangs in is
    never handled."""
    fake = _started_fake(busy_polls=2)
    fake.write_byte_data(0x41, 0xE1, 0xFF)
    fake.write_byte_data(0x41, 0x08, 0x16)
    assert fake.read_byte_data(0x41, 0x08) == 0x16 and fake.read_byte_data(0x41, 0xE1) == 0x00  # still running
    assert fake.read_byte_data(0x41, 0x08) == 0x16 and fake.read_byte_data(0x41, 0xE1) == 0x21  # handled
    assert fake.read_byte_data(0x41, 0x08) == 0x00 and not fake.int_pin_low()
    fake.write_byte_data(0x41, 0xE2, 0x20)
    assert fake.int_pin_low()
    fake.write_byte_data(0x41, 0xE1, 0x21)
    assert fake.read_byte_data(0x41, 0xE1) == 0x00 and not fake.int_pin_low()
    assert _send(fake, 0x77) == 0x06 and fake.read_byte_data(0x41, 0xE1) == 0x21  # failed, handled all the same
    fake.write_byte_data(0x41, 0xE1, 0x21)
    fake.hang(0x16)
    fake.write_byte_data(0x41, 0x08, 0x15)
    for _ in range(5):
        assert fake.read_byte_data(0x41, 0x08) == 0x16
    assert fake.read_byte_data(0x41, 0xE1) == 0x00


def test_a_command_done_enable_another_tool_left_is_cleared_at_the_start(image):
    """Another tool enabled "command done" (INT_ENAB bit 0x20). The driver waits for its commands on CMD_STAT, as ams'
    drivers do, and never clears that bit while it reads, so the start clears its enable, as ams' Linux driver's
    enable does (it enables every interrupt but this one): the measure command's done stays in INT_STATUS without
    holding the INT pin low, and records are read as ever. The other enables are kept (read-modify-write)."""
    path, data = image
    fake = SimTMF8820Bus(image=data, handover_s=0.5)
    fake.int_enab = 0x20 | 0x04
    transport = I2CTransport(1, firmware=path, smbus_factory=fake)
    transport.open()
    try:
        transport.start()
        assert fake.int_enab == 0x04 | 0x02 | 0x08 | 0x40
        assert transport.read_packet(5.0).index == 0
        assert fake.read_byte_data(0x41, 0xE1) == 0x20 and not fake.int_pin_low()
    finally:
        transport.stop()
        transport.close()
    assert fake.violations == []


class RecordingBus(SimTMF8820Bus):
    """The register fake, keeping every record read at 0x20 while measuring (the bytes of each i2c_rdwr read)."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.read_records: list[bytes] = []

    def i2c_rdwr(self, *msgs):
        super().i2c_rdwr(*msgs)
        if len(msgs) == 2 and bytes(msgs[0]) == b"\x20" and msgs[1].len > 4 and self.measuring:
            self.read_records.append(bytes(msgs[1]))


def test_a_fast_poll_never_reads_a_record_twice(image):
    """ams' Linux driver re-reads 0x20 until the TID changes because it clears the bit before it reads. The driver
    reads first and clears after: polling without pause through a slow hand-over (0x20 still holds the cleared record
    for 20 ms), every record it reads has a new TID and becomes one packet."""
    path, data = image
    fake = RecordingBus(image=data, handover_s=0.02)
    transport = I2CTransport(1, firmware=path, smbus_factory=fake, poll_s=0.0)
    transport.open()
    try:
        transport.start()
        packets = [transport.read_packet(5.0) for _ in range(62)]  # two frames
    finally:
        transport.stop()
        transport.close()
    tids = [r[1] for r in fake.read_records]
    assert len(tids) == 62 and len(set(tids)) == 62 and all(p is not None for p in packets)
    assert [getattr(p, "index", None) for p in packets] == (list(range(30)) + [None]) * 2
    assert transport.counters()["bad_records"] == 0 and fake.violations == []
