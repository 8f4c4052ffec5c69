"""The I2C backend: smbus2 messages against the register-level fake of the TMF8820.

Boot, firmware download (the fake checks checksums and that every byte arrived), accuracy mode, configuration,
interrupt enables, measure, 30 sub-packets read with i2c_rdwr; decoded histograms must equal what the fake holds, bit
for bit. The record layout is also checked against bytes built here from the protocol, independently of the fake."""

from __future__ import annotations

import asyncio
import ctypes
import logging
import re
import time
from pathlib import Path

import numpy as np
import pytest
from smbus2 import i2c_msg

from spadscan.daemon.devices import LinkLost, SensorSilent
from spadscan.daemon.sensor.assembly import FrameAssembler
from spadscan.daemon.sensor.firmware import bootloader_frame, download_frames, load_firmware
from spadscan.daemon.sensor.i2c_bus import I2CSensor, I2CTransport
from spadscan.daemon.sensor.sim_i2c import SimTMF8820Bus, frame_records
from spadscan.daemon.sensor.tmf8820 import TMF8820
from spadscan.protocol.errors import DeviceError

EXPECTED_COMMANDS = [0x6E, 0x16, 0x15, 0x10]  # short range, load config, write config, measure
NOTES = Path(__file__).resolve().parents[2] / "firmware_notes"


pytestmark = pytest.mark.usefixtures("no_leaked_threads_or_fds")


@pytest.fixture
def image(tmp_path):
    """A stand-in application image: random bytes (never the real ams image), 2.5 W_RAM chunks past a round size."""
    data = np.random.default_rng(7).integers(0, 256, 3000, dtype=np.uint8).tobytes()
    path = tmp_path / "tmf8820_app.bin"
    path.write_bytes(data)
    return path, data


async def _run(sensor, n_frames=3, during=None):
    await sensor.connect()
    try:
        await sensor.prepare()
        frames = [await sensor.next_frame(10) for _ in range(n_frames)]
        if during is not None:
            frames += await during(sensor)
        return frames
    finally:
        await sensor.release()
        await sensor.close()


def wake(fake, deadline_s=10.0):
    """Set PON on the fake as a test host and wait for cpu_ready, through the start-up without acknowledges."""
    fake.write_byte_data(0x41, 0xE0, 0x01)
    deadline = time.monotonic() + deadline_s
    while True:
        try:
            if fake.read_byte_data(0x41, 0xE0) & 0x40:
                return
        except OSError:
            pass  # the CPU is starting: nothing is acknowledged yet
        assert time.monotonic() < deadline, "cpu_ready never came"


def reference_records(counts, result_no, temperature_c, systick, distances, confidences):
    """One frame's (INT_STATUS bit, bytes) records, laid out here from the protocol as ams' drivers decode it.

    Header: RID, TID, size u16 LE. Raw histogram sub-packet n (RID 0x81): sub-header {n, payload length 128, config
    id 0}, then byte plane n // 10 of channel n % 10; its size is the message still to come without sub-headers,
    128 x (30 - n). Result (RID 0x10, size 128): number, temperature (an unsigned byte, deg C), valid count (the
    slots with a non-zero confidence), reserved, ambient, photon count, reference count, systick (u32 LE each),
    36 x {confidence, distance mm u16 LE}.
    """
    records = []
    for n in range(30):
        plane = bytes((int(v) >> (8 * (n // 10))) & 0xFF for v in counts[n % 10])
        header = bytes([0x81, n + 1]) + (128 * (30 - n)).to_bytes(2, "little") + bytes([n, 128, 0])
        records.append((0x08, header + plane))
    n_valid = sum(1 for c in confidences if c)
    head = bytes([0x10, 31]) + (128).to_bytes(2, "little") + bytes([result_no, temperature_c, n_valid, 0])
    head += b"".join(v.to_bytes(4, "little") for v in (1000, 200_000, 50_000, systick))
    body = b"".join(bytes([c]) + d.to_bytes(2, "little") for d, c in zip(distances, confidences))
    records.append((0x02, head + body))
    return records


class ReplayBus:
    """Serves prepared records as the chip does: INT_STATUS shows the next record's bit, 0x20 holds its bytes."""

    def __init__(self, records):
        self.records = list(records)

    def read_byte_data(self, addr, register, force=None):
        if register == 0x08:
            return 0x01  # CMD_STAT, checked before each frame: the measurement runs
        assert register == 0xE1
        return self.records[0][0] if self.records else 0

    def write_byte_data(self, addr, register, value, force=None):
        assert register == 0xE1
        if self.records and value & self.records[0][0]:
            self.records.pop(0)

    def i2c_rdwr(self, write, read):
        assert list(write) == [0x20]
        ctypes.memmove(read.buf, self.records[0][1][:read.len].ljust(read.len, b"\0"), read.len)

    def close(self):
        pass


def test_a_frame_laid_out_as_the_protocol_says_decodes_bit_for_bit():
    rng = np.random.default_rng(11)
    counts = rng.integers(0, 1 << 24, (10, 128))
    distances, confidences = rng.integers(0, 5000, 36).tolist(), rng.integers(0, 256, 36).tolist()
    records = reference_records(counts, 7, 200, 123457, distances, confidences)
    assert [len(r) for _, r in records] == [135] * 30 + [132]
    assert records[0][1][2:4] == b"\x00\x0f" and records[29][1][2:4] == b"\x80\x00"  # 3840 ... 128
    # The fake lays a frame out the same way, byte for byte.
    tids = iter(range(1, 100))
    result = {"result_no": 7, "temperature_c": 200, "systick": 123457, "distances_mm": distances,
              "confidences": confidences}
    assert frame_records(counts, result, True, lambda: next(tids)) == records

    transport = I2CTransport(1, smbus_factory=lambda bus: ReplayBus(records))
    transport.open()
    assembler = FrameAssembler()
    frames = [f for f in (assembler.feed(transport.read_packet(1.0)) for _ in range(31)) if f is not None]
    assert len(frames) == 1 and transport.counters()["bad_records"] == 0
    (frame,) = frames
    assert np.array_equal(frame.reference, counts[0]) and np.array_equal(frame.hists, counts[1:])
    assert frame.temperature_c == 200.0 and frame.extra["systick"] == 123457 and frame.extra["result_no"] == 7
    assert frame.extra["n_valid"] == sum(1 for c in confidences if c)
    assert frame.depths_mm == [float(d) for d in distances] and frame.confidences == confidences



def _replay(records, n_reads):
    """Read `n_reads` records of `records` through an I2CTransport; (packets, counters)."""
    transport = I2CTransport(1, smbus_factory=lambda bus: ReplayBus(records))
    transport.open()
    packets = [transport.read_packet(0.0) for _ in range(n_reads)]
    return packets, transport.counters()


def _spoil(records, ks, at, data: bytes):
    """`records` with the bytes from `at` of the records numbered in `ks` replaced by `data`."""
    return [(bit, rec[:at] + data + rec[at + len(data):]) if n in ks else (bit, rec)
            for n, (bit, rec) in enumerate(records)]


@pytest.mark.parametrize("size", [131, 3840, 0])
def test_a_size_field_other_than_the_documented_one_is_counted_not_refused(size, caplog):
    """ams' drivers place a sub-packet by its number and never check the size field after sub-packet 0: a firmware
    that writes another size (the record's own length, the total in every sub-packet) still delivers frames."""
    rng = np.random.default_rng(12)
    counts = rng.integers(0, 1 << 24, (10, 128))
    records = reference_records(counts, 7, 20, 1, list(range(36)), [9] * 36)
    with caplog.at_level(logging.WARNING, logger="spadscan.daemon"):
        packets, c = _replay(_spoil(records, (5, 6), 2, size.to_bytes(2, "little")), 31)
    assert c["bad_records"] == 0 and c["size_field_mismatches"] == 2
    assert [p.index for p in packets[:30]] == list(range(30))
    (frame,) = [f for f in map(FrameAssembler().feed, packets) if f is not None]
    assert np.array_equal(frame.reference, counts[0]) and np.array_equal(frame.hists, counts[1:])
    warned = [r.getMessage() for r in caplog.records if "size field" in r.getMessage()]
    assert warned == [f"i2c bus 1 addr 0x41: histogram sub-packet 5 has size field {size}, the protocol documents "
                      f"{128 * 25}; the sub-packets are placed by their number all the same (the size field is not "
                      f"needed for that), and such sub-packets are counted in size_field_mismatches"]


@pytest.mark.parametrize("size, refused", [(128, ""), (164, ""), (127, "result: size field 127, under 128")])
def test_a_result_whose_size_counts_diagnostics_after_its_results_is_read(size, refused):
    """ams' Linux driver reads a result's size past its 36 results as extra data (the diagnostics the register map
    puts at 0xA4-0xC7): the results stand where they do. A size too small for them is refused."""
    rng = np.random.default_rng(13)
    counts = rng.integers(0, 1 << 24, (10, 128))
    distances = rng.integers(0, 5000, 36).tolist()
    records = reference_records(counts, 7, 20, 1, distances, [9] * 36)
    bit, result = records[-1]
    records[-1] = (bit, result[:2] + size.to_bytes(2, "little") + result[4:] + bytes(max(0, size - 128)))
    packets, c = _replay(records, 31)
    frames = [f for f in map(FrameAssembler().feed, filter(None, packets)) if f is not None]
    if refused:
        assert frames == [] and c["bad_records"] == 1 and c["last_bad_record"] == refused
    else:
        assert c["bad_records"] == 0 and len(frames) == 1 and frames[0].depths_mm == [float(d) for d in distances]


def test_a_chip_that_sends_its_diagnostics_with_each_result_delivers_frames(arun, image):
    path, data = image
    fake = SimTMF8820Bus(image=data, result_diagnostics=True)
    sensor = TMF8820(I2CTransport(1, firmware=path, smbus_factory=fake))
    frames = arun(_run(sensor, n_frames=2))
    assert len(frames) == 2 and sensor.counters()["bad_records"] == 0 and fake.violations == []


@pytest.mark.parametrize("at, value, reason", [
    (0, 0x82, "histogram sub-packet: RID 0x82, not 0x81 (raw 24-bit histogram)"),
    (4, 30, "histogram sub-packet: sub-packet number 30, not 0..29"),
    (5, 64, "histogram sub-packet: sub-packet payload length 64, not 128 (one byte plane of 128 bins)"),
])
def test_a_sub_packet_that_cannot_be_placed_is_refused_with_its_reason(at, value, reason):
    records = reference_records(np.zeros((10, 128), int), 0, 20, 1, list(range(36)), [9] * 36)
    packets, c = _replay(_spoil(records, (5,), at, bytes([value])), 30)
    assert c["bad_records"] == 1 and c["last_bad_record"] == reason
    assert [p.index for p in packets[:29]] == [k for k in range(30) if k != 5]


def test_the_bootloader_echoes_the_command_it_runs_and_the_driver_waits(arun, image):
    path, data = image
    fake = SimTMF8820Bus(image=data, busy_polls=3)
    wake(fake)
    fake.violations.clear()
    fake.i2c_rdwr(i2c_msg.write(0x41, b"\x08" + bootloader_frame(0x43, b"\x00\x00")))
    statuses = []
    for _ in range(4):
        status = i2c_msg.read(0x41, 3)
        fake.i2c_rdwr(i2c_msg.write(0x41, [0x08]), status)
        statuses.append(list(status)[0])
    assert statuses == [0x43, 0x43, 0x43, 0x00]  # busy: the command is echoed; then ready

    fake = SimTMF8820Bus(image=data, busy_polls=3)
    frames = arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=1))
    assert len(frames) == 1 and fake.violations == [] and bytes(fake.ram[:len(data)]) == data


def test_a_garbled_bootloader_status_is_read_again_not_taken_for_an_error(arun, image):
    """A status whose bits a noisy bus flipped (0x00, "ready", read as 0x01, an error) fails its checksum: read again,
    it is the bootloader's own, and the download goes on. Taken as it read, it failed the start with "bootloader
    rejected"."""
    path, data = image
    fake = SimTMF8820Bus(image=data)
    fake.garbled_status_reads = 3
    frames = arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=1))
    assert len(frames) == 1 and fake.garbled_status_reads == 0 and fake.violations == []
    assert bytes(fake.ram[:len(data)]) == data


def test_measuring_enables_the_result_and_histogram_interrupts(image):
    path, data = image
    fake = SimTMF8820Bus(image=data)
    fake.int_enab = 0x10  # an enable someone else set is kept
    transport = I2CTransport(1, firmware=path, smbus_factory=fake)
    transport.open()
    try:
        transport.start()
        assert fake.int_enab == 0x10 | 0x02 | 0x08 | 0x40  # result, raw histogram and error, as ams' Linux driver
        assert fake.int_pin_low()  # the first sub-packet waits and its interrupt reaches the INT pin
        assert transport.read_packet(5.0).index == 0
        transport.stop()
        assert fake.int_enab == 0x10 and not fake.int_pin_low()
    finally:
        transport.close()
    assert fake.violations == []


def test_the_chip_is_not_addressed_while_its_cpu_starts(arun, image):
    """After PON and after RAMREMAP the chip acknowledges nothing for a while; the driver waits as the references do."""
    path, data = image
    fake = SimTMF8820Bus(image=data, startup_s=0.008)
    frames = arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=1))
    assert len(frames) == 1 and fake.violations == [] and fake.nacked_while_starting == 0


def test_a_chip_that_starts_slower_than_the_references_sleep_is_polled_until_it_answers(arun, image):
    """The 10 ms the references sleep after PON and RAMREMAP bound nothing: a CPU that starts in 40 ms (each time)
    leaves the next reads unacknowledged, which mean "not yet" (ams' drivers retry them), not a dead link."""
    path, data = image
    fake = SimTMF8820Bus(image=data, startup_s=0.04)
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake)
    frames = arun(_run(sensor, n_frames=1))
    assert len(frames) == 1 and fake.violations == [] and sensor.counters()["downloads"] == 1
    assert fake.nacked_while_starting > 0


def test_a_chip_that_never_answers_after_power_on_says_so_within_the_timeout(arun, image):
    """A chip in standby (PON 0, as a host left it) is woken by setting PON; its CPU then never answers."""
    path, data = image
    fake = SimTMF8820Bus(image=data, startup_s=60.0)
    fake.write_byte_data(0x41, 0xE0, 0x00)
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake, timeout_s=0.2)
    with pytest.raises(DeviceError, match=r"timed out after 0.2 s waiting for cpu_ready \(ENABLE bit 6\) after "
                                          r"power-on: .*no acknowledge"):
        arun(_run(sensor, n_frames=1))


def test_a_start_just_after_power_came_waits_for_the_first_acknowledge(image):
    """PON resets to 1, so a chip whose power just came starts its CPU by itself and acknowledges nothing meanwhile,
    the first ENABLE read included: "still starting" (ams' Linux driver retries that read), not a dead link."""
    path, data = image
    fake = SimTMF8820Bus(image=data, startup_s=0.05)
    transport = I2CTransport(1, firmware=path, smbus_factory=fake)
    transport.open()
    try:
        fake.power_cycle()
        transport.start()
        assert transport.read_packet(5.0).index == 0
        transport.stop()
    finally:
        transport.close()
    assert fake.nacked_while_starting > 0 and fake.violations == []
    assert transport.counters()["boots"] == 1 and transport.counters()["downloads"] == 1


def test_a_power_loss_costs_one_link_drop_and_one_start(arun, image):
    """The start after a power loss meets the chip's CPU still starting: it waits for it instead of failing as a
    second dropped link and being tried again."""
    path, data = image
    fake = SimTMF8820Bus(image=data, frame_interval_s=0.02, startup_s=0.05)
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake)

    async def during(sensor):
        fake.power_cycle()
        deadline = time.monotonic() + 10
        while sensor.counters()["reconnects"] < 1:
            assert time.monotonic() < deadline, f"never reconnected: {sensor.counters()}"
            await asyncio.sleep(0.01)
        return [await sensor.next_frame(10)]

    frames = arun(_run(sensor, n_frames=1, during=during))
    c = sensor.counters()
    assert len(frames) == 2 and c["boots"] == 2 and c["link_drops"] == 1 and c["reconnect_failures"] == 0, c
    assert c["downloads"] == 2 and fake.nacked_while_starting > 0


def test_a_sensor_not_wired_fails_in_one_line_within_the_start_up_window(arun, image):
    """Nothing on the bus answers: the wait for the first acknowledge ends after timeout_s, with one line that names
    the wait and what to check."""
    path, data = image
    fake = SimTMF8820Bus(image=data)
    fake.unplug()
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake, timeout_s=0.2)
    t0 = time.monotonic()
    with pytest.raises(DeviceError) as info:
        arun(_run(sensor, n_frames=1))
    took = time.monotonic() - t0
    assert str(info.value) == ("sensor i2c bus 1 addr 0x41: timed out after 0.2 s waiting for the sensor to answer "
                               "(ENABLE 0xe0): i2c read of register 0xe0: no acknowledge (is the sensor wired, "
                               "powered and at this address?)")
    assert 0.2 <= took < 5.0, took


def test_power_on_keeps_the_power_up_select_bits(arun, image):
    """ENABLE is read-modify-written: after a standby the chip wakes into the application kept in RAM."""
    path, data = image
    fake = SimTMF8820Bus(image=data)
    arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=1))
    assert fake.read_byte_data(0x41, 0xE0) & 0x30 == 0x20  # RAMREMAP selected "start the application in RAM"
    fake.write_byte_data(0x41, 0xE0, fake.read_byte_data(0x41, 0xE0) & ~0x01)  # a host puts it in standby
    assert fake.read_byte_data(0x41, 0xE0) == 0x22  # standby (bit 1), as ams' powerDown() requires it to read
    sensor = I2CSensor(1, smbus_factory=fake)  # no firmware: the application must still be there
    frames = arun(_run(sensor, n_frames=1))
    assert len(frames) == 1 and sensor.counters()["downloads"] == 0 and fake.violations == []
    assert fake.read_byte_data(0x41, 0xE0) & 0x30 == 0x20


def test_the_fake_measures_without_short_range_mode_or_a_written_config():
    """No invented preconditions: after RAMREMAP the application measures with its defaults."""
    fake = SimTMF8820Bus(startup_s=0.0)
    wake(fake)
    fake.i2c_rdwr(i2c_msg.write(0x41, b"\x08" + bootloader_frame(0x11)))
    assert fake.read_byte_data(0x41, 0x00) == 0x03 and fake.read_byte_data(0x41, 0x19) == 0x6F
    fake.write_byte_data(0x41, 0x08, 0x10)
    while fake.read_byte_data(0x41, 0x08) >= 0x10:
        pass
    # no HIST_DUMP: a result (0x02), the measure command handled (0x20), and with them "any interrupt" (0x01)
    assert fake.read_byte_data(0x41, 0x08) == 0x01 and fake.read_byte_data(0x41, 0xE1) == 0x23
    assert fake.violations == []


def test_boot_download_configure_measure_bit_for_bit(arun, image):
    path, data = image
    fake = SimTMF8820Bus(image=data)
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake, period_ms=250, kilo_iterations=4000)
    frames = arun(_run(sensor))
    assert fake.violations == []
    assert fake.app_running and bytes(fake.ram[:len(data)]) == data and fake.written.sum() == len(data)
    assert fake.download_seed == 0x29  # DOWNLOAD_INIT went first, as ams' C host driver sends it
    assert fake.commands == EXPECTED_COMMANDS + [0xFF]  # ... and stop on release
    assert fake.config == {"period_ms": 250, "kilo_iterations": 4000, "spad_map": 1, "hist_dump": 1,
                           "alg_setting_0": 0x04, "power_cfg": 0x00}
    assert fake.active_range == 0x6E and fake.int_enab == 0 and fake.closed  # stop disables its interrupts again
    for frame, (counts, result) in zip(frames, fake.produced):
        assert np.array_equal(frame.hists, counts[1:]) and np.array_equal(frame.reference, counts[0])
        assert frame.hists.dtype == np.uint32
        assert frame.depths_mm == [float(d) for d in result["distances_mm"]]
        assert frame.confidences == result["confidences"] and frame.temperature_c == result["temperature_c"]
        assert frame.extra["systick"] == result["systick"] and frame.extra["result_no"] == result["result_no"]
    c = sensor.counters()
    assert c["downloads"] == 1 and c["bad_records"] == 0 and c["frames_dropped"] == 0
    assert c["active_range"] == "short range"


def test_download_frames_cover_the_image_in_chunks_of_128(image):
    path, data = image
    frames = download_frames(load_firmware(path))
    labels = [label for label, _ in frames]
    assert labels[:2] == ["DOWNLOAD_INIT", "SET_ADDR 0x0000"] and labels[-1] == "RAMREMAP"
    assert len(labels) == 3 + 24  # ceil(3000/128) W_RAM frames
    assert frames[0][1][:3] == bytes([0x14, 1, 0x29])  # the seed ams' C host driver sends
    payload = b"".join(f[2:-1] for label, f in frames if label.startswith("W_RAM"))
    assert payload == data and max(f[1] for _, f in frames) == 128
    for _, f in frames:
        assert (sum(f[:-1]) + f[-1]) & 0xFF == 0xFF  # checksum: ones' complement of the byte sum


def test_the_fake_rejects_a_bad_checksum_and_an_incomplete_image():
    data = bytes(range(200))
    fake = SimTMF8820Bus(image=data, busy_polls=0)
    wake(fake)
    frame = bytearray(bootloader_frame(0x41, data[:128]))
    frame[-1] ^= 0x01
    fake.i2c_rdwr(i2c_msg.write(0x41, b"\x08" + bytes(frame)))
    status = i2c_msg.read(0x41, 3)
    fake.i2c_rdwr(i2c_msg.write(0x41, [0x08]), status)
    assert list(status)[0] == 0x02 and "checksum" in fake.violations[-1]
    fake.i2c_rdwr(i2c_msg.write(0x41, b"\x08" + bootloader_frame(0x41, data[:128])))  # the rest never comes
    fake.i2c_rdwr(i2c_msg.write(0x41, b"\x08" + bootloader_frame(0x11)))
    assert fake.read_byte_data(0x41, 0x00) == 0x80 and "72 image bytes missing" in fake.violations[-1]
    with pytest.raises(ValueError):
        fake.read_i2c_block_data(0x41, 0x20, 33)  # as smbus2: SMBus block reads stop at 32 bytes


def test_a_truncated_download_is_a_named_error(arun, image, tmp_path):
    path, data = image
    short = tmp_path / "short.bin"
    short.write_bytes(data[:2000])
    sensor = I2CSensor(1, firmware=short, smbus_factory=SimTMF8820Bus(image=data), timeout_s=0.2)
    with pytest.raises(DeviceError, match=r"sensor i2c bus 1 addr 0x41: timed out after 0.2 s waiting for the "
                                          r"application to start after the download of .*short.bin"):
        arun(_run(sensor))


def test_the_app_already_running_is_stopped_and_reused(arun, image):
    path, data = image
    fake = SimTMF8820Bus(image=data)
    arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=1))
    before = len(fake.produced)
    frames = arun(_run(I2CSensor(1, smbus_factory=fake), n_frames=1))  # no firmware needed: it still runs
    assert fake.violations == [] and len(frames) == 1
    assert fake.commands == EXPECTED_COMMANDS + [0xFF, 0xFF] + EXPECTED_COMMANDS[1:] + [0xFF]
    assert np.array_equal(frames[0].hists, fake.produced[before][0][1:])  # the first frame of the new session


def test_a_start_after_another_tool_sets_the_result_reporting_back_to_ams_reset_value(arun, image):
    """The application keeps its configuration while it stays powered: one that another tool left reporting
    statistics and diagnostics (ALG_SETTING_0 0x46) is set back to distances only (0x04, ams' reset value) at the
    daemon's start, as every setting the daemon relies on is."""
    path, data = image
    fake = SimTMF8820Bus(image=data)
    arun(_run(I2CSensor(1, firmware=path, smbus_factory=fake), n_frames=1))
    fake.config["alg_setting_0"] = 0x46  # left so by another tool; the application still runs
    frames = arun(_run(I2CSensor(1, smbus_factory=fake), n_frames=2))
    assert fake.violations == [] and len(frames) == 2
    assert fake.config["alg_setting_0"] == 0x04


@pytest.mark.parametrize("fake_kw, sensor_kw, message", [
    ({"app_id": 0x42}, {}, r"unexpected APP_ID 0x42 \(expected 0x80 for the bootloader or 0x03"),
    ({"ready_after_polls": None}, {}, r"timed out after 0.2 s waiting for cpu_ready \(ENABLE bit 6\)"),
    ({}, {"firmware": None}, r"the sensor is in its bootloader and needs the firmware image"),
    ({"address": 0x29}, {}, r"timed out after 0.2 s waiting for the sensor to answer \(ENABLE 0xe0\): i2c read of "
                            r"register 0xe0: no acknowledge \(is the sensor wired, powered and at this address\?\)$"),
])
def test_boot_failures_are_named(arun, image, fake_kw, sensor_kw, message):
    path, data = image
    kw = {"firmware": path, **sensor_kw}
    sensor = I2CSensor(1, smbus_factory=SimTMF8820Bus(image=data, **fake_kw), timeout_s=0.2, **kw)
    with pytest.raises(DeviceError, match=r"^sensor i2c bus 1 addr 0x41: " + message):
        arun(_run(sensor))


def test_a_missing_firmware_file_is_one_line_naming_the_path(arun, tmp_path):
    missing = tmp_path / "nowhere" / "tmf8820_app.hex"
    with pytest.raises(DeviceError) as info:
        arun(_run(I2CSensor(1, firmware=missing, smbus_factory=SimTMF8820Bus())))
    assert str(missing) in str(info.value) and "\n" not in str(info.value) and "does not exist" in str(info.value)


def test_intel_hex_images(tmp_path):
    def record(kind, addr, data):
        body = bytes([len(data), addr >> 8, addr & 0xFF, kind]) + data
        return ":" + (body + bytes([-sum(body) & 0xFF])).hex().upper()

    lines = [record(4, 0, b"\x20\x00"), record(0, 0x0000, b"\x01\x02"), record(0, 0x0002, b"\x03"),
             record(0, 0x0100, b"\x09"), record(1, 0, b"")]
    path = tmp_path / "app.hex"
    path.write_text("\n".join(lines))
    assert load_firmware(path).segments == ((0x0000, b"\x01\x02\x03"), (0x0100, b"\x09"))
    path.write_text(lines[1][:-2] + "00")
    with pytest.raises(DeviceError, match=r"app.hex: line 1 is not an Intel HEX record"):
        load_firmware(path)
    # An extended segment address (type 02) moves the data that follows (base = segment x 16), as type 04 does.
    path.write_text("\n".join([record(2, 0, b"\x01\x00"), record(0, 0x0000, b"\xaa\xbb"), record(1, 0, b"")]))
    assert load_firmware(path).segments == ((0x1000, b"\xaa\xbb"),)


@pytest.mark.parametrize("name", ["app.ihex", "app.hex.txt", "app.bin"])
def test_a_hex_image_is_known_by_its_content_whatever_its_name(tmp_path, name):
    """ams' HEX image saved under another name (.ihex, a browser's .hex.txt) was downloaded as a raw binary: its text
    went into the chip's RAM. HEX is known by its records; other text is refused."""
    body = bytes([3, 0x00, 0x10, 0x00]) + b"\x01\x02\x03"
    text = ":" + (body + bytes([-sum(body) & 0xFF])).hex().upper() + "\n:00000001FF\n"
    path = tmp_path / name
    path.write_text(text)
    assert load_firmware(path).segments == ((0x0010, b"\x01\x02\x03"),)
    path.write_text("this is a README, not an image\n")
    with pytest.raises(DeviceError, match=r"is text, neither Intel HEX .* nor a raw binary image"):
        load_firmware(path)
    path.write_bytes(bytes(range(256)))  # a raw binary image loads as it is
    assert load_firmware(path).segments == ((0, bytes(range(256))),)


@pytest.mark.parametrize("size_field", ["remaining", "total"])
def test_frames_arrive_whichever_size_field_the_firmware_writes(arun, image, size_field):
    """The fake writes the documented size (the message still to come) or the total in every sub-packet; the
    driver delivers the same frames from both, and counts the sub-packets whose size is not the documented one."""
    path, data = image
    tids = iter(range(1, 100))
    result = {"result_no": 0, "temperature_c": 20, "systick": 1, "distances_mm": [0] * 36, "confidences": [0] * 36}
    laid_out = frame_records(np.zeros((10, 128), int), result, True, lambda: next(tids), size_field)
    sizes = [rec[2] | rec[3] << 8 for _, rec in laid_out[:30]]
    assert sizes == ([128 * (30 - k) for k in range(30)] if size_field == "remaining" else [3840] * 30)

    fake = SimTMF8820Bus(image=data, size_field=size_field)
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake)
    frames = arun(_run(sensor, n_frames=2))
    assert fake.violations == [] and len(frames) == 2
    for frame, (counts, _) in zip(frames, fake.produced):
        assert np.array_equal(frame.hists, counts[1:]) and np.array_equal(frame.reference, counts[0])
    c = sensor.counters()
    assert c["bad_records"] == 0 and c["frames_dropped"] == 0
    if size_field == "remaining":
        assert c["size_field_mismatches"] == 0
    else:
        assert c["size_field_mismatches"] >= 2 * 29  # every sub-packet but the first of each frame


def test_no_frame_because_records_are_refused_says_so(arun, image):
    """A firmware whose records the driver refuses: the sensor answers and records arrive, but no frame is ever
    made; the timeout names the refused records and why the last one was refused."""
    path, data = image
    fake = SimTMF8820Bus(image=data)
    fake.corrupt_next_record(0, frames=None)  # sub-packet 0 of every frame has another RID
    sensor = I2CSensor(1, firmware=path, smbus_factory=fake)

    async def main():
        await sensor.connect()
        try:
            await sensor.prepare()
            while sensor.counters()["bad_records"] == 0:
                await asyncio.sleep(0.01)
            with pytest.raises(SensorSilent) as info:
                await sensor.next_frame(0.1)
            return info.value
        finally:
            await sensor.release()
            await sensor.close()

    exc = arun(main())
    detail = re.fullmatch(r"(\d+) records? arrived since the last frame but (was|were) refused \(bad_records\); the "
                          r"last one: histogram sub-packet: RID 0x7f, not 0x81 \(raw 24-bit histogram\)", exc.detail)
    assert detail and int(detail[1]) >= 1
    assert str(exc) == f"sensor i2c bus 1 addr 0x41: no complete frame within 0.1 s; {exc.detail}"
    assert sensor.counters()["frames"] == 0


def test_a_corrupt_record_drops_its_frame(arun, image):
    path, data = image
    fake = SimTMF8820Bus(image=data)

    def index_of(frame):
        """Which produced frame this is (bit for bit), or None."""
        return next((k for k, (counts, _) in enumerate(fake.produced)
                     if np.array_equal(frame.reference, counts[0]) and np.array_equal(frame.hists, counts[1:])), None)

    async def during(sensor):
        fake.corrupt_next_record(11)
        got = []
        while not (fake.spoiled and got and got[-1] > fake.spoiled[0]):  # read until past the spoiled frame
            got.append(index_of(await sensor.next_frame(10)))
        return got

    sensor = I2CSensor(1, firmware=path, smbus_factory=fake)
    first, *rest = arun(_run(sensor, n_frames=1, during=during))
    (spoiled,) = fake.spoiled
    assert index_of(first) == 0 and None not in rest
    assert rest == [k for k in range(1, rest[-1] + 1) if k != spoiled]  # every frame but the spoiled one, in order
    c = sensor.counters()
    assert c["bad_records"] == 1 and c["frames_dropped"] == 1 and c["dropped_out_of_order"] == 1


def test_power_loss_and_unplug_reboot_and_download_again(arun, image):
    path, data = image
    fake = SimTMF8820Bus(image=data, frame_interval_s=0.02)

    async def during(sensor):
        out = []
        fake.power_cycle()
        out.append(await sensor.next_frame(10))
        fake.unplug()
        with pytest.raises(LinkLost, match="i2c bus 1 addr 0x41: link down .*no acknowledge"):
            await sensor.next_frame(30)
        fake.replug()
        while sensor.counters()["link"] == "down":
            await asyncio.sleep(0.01)
        out.append(await sensor.next_frame(10))
        return out

    sensor = I2CSensor(1, firmware=path, smbus_factory=fake, link_grace_s=0.3)
    frames = arun(_run(sensor, n_frames=1, during=during))
    c = sensor.counters()
    assert c["downloads"] == 3 and c["link_drops"] == 2 and c["reconnects"] == 2
    held = [counts for counts, _ in fake.produced]
    for f in frames:
        assert any(np.array_equal(f.hists, h[1:]) and np.array_equal(f.reference, h[0]) for h in held)


def test_a_chip_reset_is_caught_by_the_watchdog(arun, image):
    path, data = image
    fake = SimTMF8820Bus(image=data, frame_interval_s=0.02)
    transport = I2CTransport(1, firmware=path, smbus_factory=fake, watchdog_s=0.2)
    sensor = TMF8820(transport)

    async def during(sensor):
        fake.crash()  # back in the bootloader but still answering: only APP_ID tells
        while sensor.counters()["reconnects"] < 1:
            await asyncio.sleep(0.01)
        return [await sensor.next_frame(10)]

    arun(_run(sensor, n_frames=1, during=during))
    c = sensor.counters()
    assert c["downloads"] == 2 and "sensor reset (APP_ID 0x80" in c["last_link_error"]


def test_a_chip_that_reads_ok_while_it_measures_is_waited_for_not_restarted(arun, image):
    """CMD_STAT 0x00 (ok) while measuring is as good as 0x01 (accepted) to ams' Linux driver: a record later than the
    watchdog's wait is waited for, the chip not booted again."""
    path, data = image
    fake = SimTMF8820Bus(image=data, frame_interval_s=0.4, measure_stat=0x00)
    sensor = TMF8820(I2CTransport(1, firmware=path, smbus_factory=fake, watchdog_s=0.1))
    frames = arun(_run(sensor, n_frames=2))
    c = sensor.counters()
    assert len(frames) == 2 and c["reconnects"] == 0 and c["boots"] == 1, c


def test_an_application_that_stops_measuring_is_started_again(arun, image):
    """CMD_STAT 0x03 (ams: "severe error, stopped", APPLICATION_STATUS says why) leaves APP_ID at 0x03: the watchdog
    must still restart the measurement instead of reporting a silent sensor forever."""
    path, data = image
    fake = SimTMF8820Bus(image=data, frame_interval_s=0.02)
    transport = I2CTransport(1, firmware=path, smbus_factory=fake, watchdog_s=0.2)
    sensor = TMF8820(transport)

    async def during(sensor):
        fake.stop_measuring(cmd_stat=0x03, app_status=0x04, error_interrupt=False)  # only the watchdog can tell
        deadline = time.monotonic() + 10
        while sensor.counters()["reconnects"] < 1:
            assert time.monotonic() < deadline, f"never restarted: {sensor.counters()}"
            await asyncio.sleep(0.01)
        return [await sensor.next_frame(10)]

    arun(_run(sensor, n_frames=1, during=during))
    c = sensor.counters()
    assert c["downloads"] == 1 and c["boots"] == 2 and fake.violations == []  # the application in RAM is reused
    assert ("sensor stopped measuring (CMD_STAT 0x03 (application error, stopped), APPLICATION_STATUS 0x04, no record "
            "for 0.2 s)") in c["last_link_error"]
    assert fake.commands.count(0x10) == 2


def _started(image, **fake_kw):
    path, data = image
    fake = SimTMF8820Bus(image=data, **fake_kw)
    transport = I2CTransport(1, firmware=path, smbus_factory=fake)
    transport.open()
    transport.start()
    return fake, transport


def test_clearing_the_interrupt_before_reading_the_record_loses_nothing(image):
    """ams' Python and Arduino drivers clear INT_STATUS and then read 0x20; the chip hands the next record over only
    a moment after the clear, so that order reads every record, each with a new TID."""
    fake, transport = _started(image, handover_s=0.02)
    try:
        got = []
        for _ in range(31):
            while not (status := fake.read_byte_data(0x41, 0xE1)) & 0x0A:
                pass
            fake.write_byte_data(0x41, 0xE1, status & 0x0A)
            read = i2c_msg.read(0x41, 135)
            fake.i2c_rdwr(i2c_msg.write(0x41, [0x20]), read)
            got.append(bytes(read))
    finally:
        transport.stop()
        transport.close()
    assert [r[4] for r in got[:30]] == list(range(30)) and [r[0] for r in got] == [0x81] * 30 + [0x10]
    assert len({r[1] for r in got}) == 31  # a new TID with every record, as ams' Linux driver waits for
    counts, _ = fake.produced[0]
    assert got[13][7:] == ((counts[3] >> 8) & 0xFF).astype(np.uint8).tobytes()


def test_a_record_flagged_when_the_measurement_restarts_is_not_read_as_the_new_ones(image):
    """A stop leaves the record handed over flagged until the host clears it (ams' drivers all clear INT_STATUS
    themselves around a stop or start): a restart that did not would read the stopped measurement's sub-packet as
    the first record of the new one. The first record read after a restart is sub-packet 0."""
    from spadscan.daemon.sensor.transport import HistogramPacket

    fake, transport = _started(image, frame_interval_s=0.02)
    try:
        while True:  # into a frame: its sub-packets 0-5 read, 6 waits flagged
            pkt = transport.read_packet(10)
            assert pkt is not None, "no record in 10 s"
            if isinstance(pkt, HistogramPacket) and pkt.index == 5:
                break
        deadline = time.monotonic() + 10
        while not fake.read_byte_data(0x41, 0xE1) & 0x08:
            assert time.monotonic() < deadline, "sub-packet 6 never flagged"
        transport.restart()
        first = transport.read_packet(10)
    finally:
        transport.stop()
        transport.close()
    assert isinstance(first, HistogramPacket) and first.index == 0, first


def test_the_chip_measures_on_its_own_period_while_the_host_is_away(image):
    """The chip does not wait for the host to measure: frames measured while one is handed over replace each other
    in its buffer (lost), and the host gets the newest."""
    fake, transport = _started(image, frame_interval_s=0.01)
    try:
        deadline = time.monotonic() + 30
        while not fake.produced:  # int_pin_low lets the chip's clock run without reading anything
            fake.int_pin_low()
            assert time.monotonic() < deadline, "the chip never measured"
        lost_before = fake.lost  # a busy test machine may call late: measurements missed before the first one sent
        while fake.lost < lost_before + 3:
            fake.int_pin_low()
            assert time.monotonic() < deadline, "the chip stopped measuring"
        assembler = FrameAssembler()
        frames = []
        while len(frames) < 2:
            frame = assembler.feed(transport.read_packet(5.0))
            if frame is not None:
                frames.append(frame)
    finally:
        transport.stop()
        transport.close()
    first, second = frames
    sent_first = fake.produced[0][1]["result_no"]
    assert first.extra["result_no"] == sent_first
    assert second.extra["result_no"] >= sent_first + 4  # the three and more after the first were never sent
    (counts, result), = [p for p in fake.produced if p[1]["result_no"] == second.extra["result_no"]][-1:]
    assert np.array_equal(second.hists, counts[1:]) and assembler.counters()["frames_dropped"] == 0


def test_a_host_slower_than_the_chip_loses_whole_frames_never_mixes_them(arun, image):
    """A chip that holds a record only hold_s abandons the rest of a frame the host is too slow for: the host sees a
    torn frame, drops it (counted) and stores only whole frames, bit for bit."""
    path, data = image
    # hold_s well above a busy machine's pause between two reads: only the stalls below tear a frame
    fake = SimTMF8820Bus(image=data, hold_s=0.25)
    slow = {"reads": 0}

    class SlowHost:
        """The fake as the bus, but the host stalls past hold_s after every third read of sub-packet 12 (from the
        second on). A stall tears that frame, and its late clear also clears the next frame's sub-packet 0, which
        costs that frame too: the frame after those two comes whole."""

        def __call__(self, bus):
            fake(bus)
            return self

        def __getattr__(self, name):
            return getattr(fake, name)

        def i2c_rdwr(self, *msgs):
            fake.i2c_rdwr(*msgs)
            record = bytes(msgs[-1])
            if len(msgs) == 2 and list(msgs[0]) == [0x20] and record[0] == 0x81 and record[4] == 12:
                slow["reads"] += 1
                if slow["reads"] % 3 == 2:
                    time.sleep(3 * fake.hold_s)  # the stall itself: the host is busy between read and clear

    def index_of(frame):
        return next((k for k, (counts, _) in enumerate(fake.produced)
                     if np.array_equal(frame.reference, counts[0]) and np.array_equal(frame.hists, counts[1:])), None)

    sensor = I2CSensor(1, firmware=path, smbus_factory=SlowHost())
    frames = arun(_run(sensor, n_frames=3))
    delivered = [index_of(f) for f in frames]
    assert None not in delivered and delivered == sorted(delivered)
    assert fake.torn and not set(delivered) & set(fake.torn)
    c = sensor.counters()
    assert c["frames_dropped"] >= 1 and c["frames"] == 3 and c["bad_records"] == 0


def test_bad_settings_are_refused():
    with pytest.raises(DeviceError, match="period_ms = 0 must be an integer in"):
        I2CSensor(1, period_ms=0)
    with pytest.raises(DeviceError, match="kilo_iterations = 70000"):
        I2CSensor(1, kilo_iterations=70000)
    with pytest.raises(DeviceError, match="spad_map = 7 is time-multiplexed"):
        I2CSensor(1, spad_map=7)
    for user_mask in (14, 16, 255):  # the config page's SPAD_MAP_ID is 4 bits; 14 needs the SPAD config page
        with pytest.raises(DeviceError, match=f"spad_map = {user_mask} is none of ams' predefined SPAD maps"):
            I2CSensor(1, spad_map=user_mask)


def test_the_lab_notes_list_exactly_the_notes_there_are():
    readme = (NOTES / "README.md").read_text()
    listed = set(re.findall(r"\]\(([^)#]+\.md)\)", readme))
    assert listed == {p.name for p in NOTES.glob("*.md")} - {"README.md"}
    assert {"modes.md", "calibration.md"} <= listed
