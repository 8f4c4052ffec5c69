"""The TMF8820 on an I2C bus (smbus2): boot, firmware download, short-range mode, configuration and readout.

The sequence `start` runs (the fake in `sim_i2c` enforces the same order):

1. ENABLE 0xE0 <- 0x01 (PON); poll ENABLE until bit 6 (cpu_ready) is set.
2. APP_ID 0x00: 0x80 = bootloader -> download the image; 0x03 = the application already runs (no power loss since
   the last download) -> stop it (0xFF) in case a previous session left it measuring; anything else is an error.
3. Download: bootloader frames written to 0x08 with `i2c_rdwr` (up to 131 bytes, beyond SMBus's 32): SET_ADDR, then
   W_RAM chunks of <= 128 bytes; after each, the 3-byte bootloader status at 0x08 (`[status, 0, ~status]`) is
   polled while busy (0x10) and must read 0x00. RAMREMAP then hands over to the application, so instead of the
   bootloader's status we poll APP_ID until it reads 0x03.
4. CMD_STAT 0x08 <- 0x6E (short-range high-accuracy mode), then 0x16 (load the common config page; 0x20 reads 0x16),
   config registers period ms 0x24 (u16 LE), kilo-iterations 0x26 (u16 LE), SPAD map 0x34, HIST_DUMP 0x39 = 1 (raw
   histograms), then 0x15 (write config). After each command CMD_STAT reads the command while busy, then 0x00 (ok)
   or 0x01 (accepted); 0x02..0x0F are errors.
5. INT_STATUS 0xE1 <- 0xFF (clear), CMD_STAT <- 0x10 (measure).

Readout polls INT_STATUS: bit 0x08 = a histogram sub-packet waits at 0x20 (135 bytes: RID 0x81, TID, size LE 131,
sub-packet no, payload len 128, config, 128 bytes), bit 0x02 = a result (132 bytes: RID 0x10, TID, size LE 128,
result no, temperature int8, n valid, reserved, ambient u32, photon count u32, reference count u32, systick u32,
36 x {confidence u8, distance mm u16 LE}). Each is read in one `i2c_rdwr` transfer and its bit cleared by writing it
back. If no record arrives for `watchdog_s`, APP_ID is checked: a sensor that lost power is back in its bootloader,
which the device treats as a dropped link (it boots and downloads again).
"""

from __future__ import annotations

import errno
import time
from pathlib import Path
from typing import Callable

from spadscan.protocol.errors import DeviceError
from spadscan.protocol.sensor_model import SensorModel

from .firmware import FirmwareImage, download_frames, load_firmware
from .tmf8820 import TMF8820
from .transport import N_RESULTS, N_SUBPACKETS, SUBPACKET_BYTES, HistogramPacket, LinkDown, Packet, ResultPacket, Transport

REG_APP_ID, REG_CMD_STAT, REG_PAGE, REG_ENABLE, REG_INT_STATUS = 0x00, 0x08, 0x20, 0xE0, 0xE1
REG_PERIOD, REG_KILO_ITER, REG_SPAD_MAP, REG_HIST_DUMP = 0x24, 0x26, 0x34, 0x39
APP_BOOTLOADER, APP_RUNNING = 0x80, 0x03
CMD_MEASURE, CMD_STOP, CMD_LOAD_CONFIG, CMD_WRITE_CONFIG, CMD_SHORT_RANGE = 0x10, 0xFF, 0x16, 0x15, 0x6E
INT_RESULT, INT_HISTOGRAM = 0x02, 0x08
HIST_RECORD, RESULT_RECORD = 7 + SUBPACKET_BYTES, 24 + 3 * N_RESULTS  # 135 and 132 bytes
BL_BUSY = 0x10
BL_ERRORS = {0x01: "size error", 0x02: "checksum error", 0x03: "resource error", 0x04: "application error",
             0x05: "timeout", 0x06: "locked", 0x07: "address out of range", 0x08: "more data expected"}
COMMAND_NAMES = {CMD_MEASURE: "measure", CMD_STOP: "stop", CMD_LOAD_CONFIG: "load common config",
                 CMD_WRITE_CONFIG: "write config", CMD_SHORT_RANGE: "short-range mode"}


def parse_histogram_record(buf: bytes, t: float) -> HistogramPacket | None:
    """A 135-byte histogram record, or None when its header is not one."""
    if (len(buf) != HIST_RECORD or buf[0] != 0x81 or buf[2] | buf[3] << 8 != HIST_RECORD - 4
            or buf[4] >= N_SUBPACKETS or buf[5] != SUBPACKET_BYTES):
        return None
    return HistogramPacket(index=buf[4], payload=bytes(buf[7:]), t=t)


def parse_result_record(buf: bytes, t: float) -> ResultPacket | None:
    """A 132-byte result record, or None when its header is not one."""
    if len(buf) != RESULT_RECORD or buf[0] != 0x10 or buf[2] | buf[3] << 8 != RESULT_RECORD - 4 or buf[6] > N_RESULTS:
        return None
    u32 = [int.from_bytes(buf[k:k + 4], "little") for k in (8, 12, 16, 20)]
    body = buf[24:]
    return ResultPacket(result_no=buf[4], temperature_c=float(buf[5] - 256 if buf[5] > 127 else buf[5]),
                        n_valid=buf[6], systick=u32[3],
                        distances_mm=[body[3 * k + 1] | body[3 * k + 2] << 8 for k in range(N_RESULTS)],
                        confidences=[body[3 * k] for k in range(N_RESULTS)], t=t,
                        extra={"ambient": u32[0], "photon_count": u32[1], "reference_count": u32[2]})


class I2CTransport(Transport):
    """smbus2 link to a TMF8820 at `address` on `bus` (a number or a /dev/i2c-N path).

    smbus_factory(bus) returns an SMBus-like object (default `smbus2.SMBus`; tests pass the fake). Counters:
    records, bad_records, boots, downloads.
    """

    def __init__(self, bus: int | str, address: int = 0x41, firmware: Path | None = None, *, period_ms: int = 100,
                 kilo_iterations: int = 4000, spad_map: int = 1, smbus_factory: Callable | None = None,
                 poll_s: float = 0.002, timeout_s: float = 1.0, watchdog_s: float = 3.0):
        for key, v, hi in (("period_ms", period_ms, 0xFFFF), ("kilo_iterations", kilo_iterations, 0xFFFF),
                           ("spad_map", spad_map, 0xFF), ("address", address, 0x7F)):
            if not (isinstance(v, int) and 0 < v <= hi):
                raise DeviceError(f"i2c sensor: {key} = {v} must be an integer in [1, {hi}]")
        self.bus_id, self.address = bus, address
        self.firmware_path = None if firmware is None else Path(firmware)
        self.period_ms, self.kilo_iterations, self.spad_map = period_ms, kilo_iterations, spad_map
        self.poll_s, self.timeout_s, self.watchdog_s = poll_s, timeout_s, watchdog_s
        self.name = f"i2c bus {bus} addr {address:#04x}"
        self._factory = smbus_factory
        self._bus = None
        self._image: FirmwareImage | None = None
        self._last_record = 0.0
        self._counts = {"records": 0, "bad_records": 0, "boots": 0, "downloads": 0}

    # ---- lifecycle -----------------------------------------------------------------------------------------------
    def open(self) -> None:
        if self.firmware_path is not None and self._image is None:
            self._image = load_firmware(self.firmware_path)  # a missing file fails here, before the bus is touched
        if self._bus is not None:
            return
        if self._factory is None:
            import smbus2

            self._factory = smbus2.SMBus
        try:
            self._bus = self._factory(self.bus_id)
        except (OSError, ValueError) as exc:
            raise LinkDown(f"cannot open i2c bus {self.bus_id}: {exc}") from None

    def start(self) -> None:
        self._counts["boots"] += 1
        self._write(REG_ENABLE, 0x01)
        self._wait(lambda: self._read(REG_ENABLE) & 0x40, "cpu_ready (ENABLE bit 6) after power-on")
        app = self._read(REG_APP_ID)
        if app == APP_BOOTLOADER:
            self._download()
        elif app == APP_RUNNING:
            self._command(CMD_STOP)
        else:
            raise DeviceError(f"unexpected APP_ID {app:#04x} (expected {APP_BOOTLOADER:#04x} for the bootloader or "
                              f"{APP_RUNNING:#04x} for the application): is this a TMF8820?")
        self._command(CMD_SHORT_RANGE)
        self._command(CMD_LOAD_CONFIG)
        page = self._read(REG_PAGE)
        if page != CMD_LOAD_CONFIG:
            raise DeviceError(f"config page did not load: register 0x20 reads {page:#04x}, expected 0x16")
        self._block_write(REG_PERIOD, [self.period_ms & 0xFF, self.period_ms >> 8])
        self._block_write(REG_KILO_ITER, [self.kilo_iterations & 0xFF, self.kilo_iterations >> 8])
        self._write(REG_SPAD_MAP, self.spad_map)
        self._write(REG_HIST_DUMP, 0x01)
        self._command(CMD_WRITE_CONFIG)
        self._write(REG_INT_STATUS, 0xFF)
        self._command(CMD_MEASURE)
        self._last_record = time.monotonic()

    def stop(self) -> None:
        if self._bus is not None:
            self._command(CMD_STOP)

    def close(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            try:
                bus.close()
            except OSError:
                pass

    def counters(self) -> dict:
        return dict(self._counts)

    # ---- readout -------------------------------------------------------------------------------------------------
    def read_packet(self, timeout_s: float) -> Packet | None:
        deadline = time.monotonic() + timeout_s
        while True:
            status = self._read(REG_INT_STATUS)
            if status & (INT_HISTOGRAM | INT_RESULT):
                bit = INT_HISTOGRAM if status & INT_HISTOGRAM else INT_RESULT
                buf = self._block_read(REG_PAGE, HIST_RECORD if bit == INT_HISTOGRAM else RESULT_RECORD)
                t = time.monotonic()
                self._write(REG_INT_STATUS, bit)
                pkt = (parse_histogram_record if bit == INT_HISTOGRAM else parse_result_record)(buf, t)
                self._last_record = t
                if pkt is not None:
                    self._counts["records"] += 1
                    return pkt
                self._counts["bad_records"] += 1
                continue
            now = time.monotonic()
            if now - self._last_record > self.watchdog_s:
                self._last_record = now
                app = self._read(REG_APP_ID)
                if app != APP_RUNNING:
                    raise LinkDown(f"sensor reset (APP_ID {app:#04x}, no record for {self.watchdog_s:g} s)")
            if now >= deadline:
                return None
            time.sleep(min(self.poll_s, max(0.0, deadline - now)))

    # ---- boot steps ----------------------------------------------------------------------------------------------
    def _download(self) -> None:
        if self._image is None:
            raise DeviceError("the sensor is in its bootloader and needs the firmware image: set the path to your "
                              "copy of the ams TMF8820 application image (firmware = PATH)")
        self._counts["downloads"] += 1
        for label, frame in download_frames(self._image):
            self._rdwr_write(bytes([REG_CMD_STAT]) + frame)
            if label != "RAMREMAP":
                self._bootloader_ok(label)
        self._wait(lambda: self._read(REG_APP_ID) == APP_RUNNING,
                   f"the application to start after the download of {self._image.path} (APP_ID 0x03)")

    def _bootloader_ok(self, label: str) -> None:
        def ready():
            status, size, csum = self._block_read(REG_CMD_STAT, 3)
            if csum != ~(status + size) & 0xFF:
                return False  # a garbled status read: read it again
            if status == BL_BUSY:
                return False
            if status != 0x00:
                raise DeviceError(f"bootloader rejected {label}: {BL_ERRORS.get(status, 'error')} "
                                  f"(status {status:#04x})")
            return True

        self._wait(ready, f"the bootloader to accept {label}")

    def _command(self, cmd: int) -> None:
        name = f"command {cmd:#04x} ({COMMAND_NAMES[cmd]})"
        self._write(REG_CMD_STAT, cmd)

        def done():
            status = self._read(REG_CMD_STAT)
            if status >= 0x10:
                return False
            if status > 0x01:
                raise DeviceError(f"{name} failed with status {status:#04x}")
            return True

        self._wait(done, name)

    def _wait(self, ready: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + self.timeout_s
        while not ready():
            if time.monotonic() >= deadline:
                raise DeviceError(f"timed out after {self.timeout_s:g} s waiting for {what}")
            time.sleep(self.poll_s)

    # ---- bus access: every failure is a dropped link ---------------------------------------------------------------
    def _read(self, reg: int) -> int:
        try:
            return self._need_bus().read_byte_data(self.address, reg)
        except OSError as exc:
            raise _bus_error(f"read of register {reg:#04x}", exc) from None

    def _write(self, reg: int, value: int) -> None:
        try:
            self._need_bus().write_byte_data(self.address, reg, value)
        except OSError as exc:
            raise _bus_error(f"write of register {reg:#04x}", exc) from None

    def _block_write(self, reg: int, data: list[int]) -> None:
        try:
            self._need_bus().write_i2c_block_data(self.address, reg, data)
        except OSError as exc:
            raise _bus_error(f"block write at {reg:#04x}", exc) from None

    def _block_read(self, reg: int, n: int) -> bytes:
        """n bytes from reg in one combined transfer (SMBus block reads stop at 32 bytes)."""
        from smbus2 import i2c_msg

        write, read = i2c_msg.write(self.address, [reg]), i2c_msg.read(self.address, n)
        try:
            self._need_bus().i2c_rdwr(write, read)
        except OSError as exc:
            raise _bus_error(f"read of {n} bytes at {reg:#04x}", exc) from None
        return bytes(read)

    def _rdwr_write(self, data: bytes) -> None:
        from smbus2 import i2c_msg

        try:
            self._need_bus().i2c_rdwr(i2c_msg.write(self.address, data))
        except OSError as exc:
            raise _bus_error(f"write of {len(data)} bytes", exc) from None

    def _need_bus(self):
        if self._bus is None:
            raise LinkDown("the bus is not open")
        return self._bus


def _bus_error(what: str, exc: OSError) -> LinkDown:
    """A failed transfer as a dropped link; a missing acknowledge says what to check."""
    if exc.errno in (errno.EREMOTEIO, errno.ENXIO, errno.EIO):
        return LinkDown(f"i2c {what}: no acknowledge (is the sensor wired, powered and at this address?)")
    return LinkDown(f"i2c {what} failed: {exc}")


class I2CSensor(TMF8820):
    """A TMF8820 on I2C `bus` at `address`; `firmware` is the path to the user's copy of the application image.

    period_ms: measurement period (the sensor runs back to back when a measurement takes longer); kilo_iterations:
    laser cycles per measurement in thousands (4000 ~ the ~4 M cycles fitted to LCSPCData's captures).
    """

    def __init__(self, bus: int | str, address: int = 0x41, firmware: Path | None = None, *,
                 model: SensorModel | None = None, period_ms: int = 100, kilo_iterations: int = 4000,
                 spad_map: int = 1, smbus_factory: Callable | None = None, frame_timeout_s: float = 2.0,
                 link_grace_s: float = 5.0, timeout_s: float = 1.0, queue_frames: int = 256):
        transport = I2CTransport(bus, address, firmware, period_ms=period_ms, kilo_iterations=kilo_iterations,
                                 spad_map=spad_map, smbus_factory=smbus_factory, timeout_s=timeout_s)
        super().__init__(transport, model=model, frame_timeout_s=frame_timeout_s, link_grace_s=link_grace_s,
                         queue_frames=queue_frames)
