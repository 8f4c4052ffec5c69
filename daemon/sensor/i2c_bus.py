"""The TMF8820 on an I2C bus (smbus2): boot, firmware download, accuracy mode, configuration and readout.

The sequence `start` runs (the facts come from ams' Python, Linux and Arduino drivers; the fake in `sim_i2c` models
the chip the same way):

1. Power on: read ENABLE 0xE0; unless PON (bit 0) and cpu_ready (bit 6) are set, write it back with PON set. This is
   a read-modify-write: the power-up select bits 4:5 say what the CPU starts after a wake-up (2: the application in
   RAM, which RAMREMAP sets) and must survive; the cpu_reset bit 7 is never written. Then wait SETTLE_S (10 ms, as
   the references do: the chip does not answer while its CPU starts) and poll ENABLE until cpu_ready. A chip whose
   power just came starts its CPU by itself (PON resets to 1) and answers nothing meanwhile, the first ENABLE read
   included: that read is retried until timeout_s, as ams' Linux driver retries it; a sensor that never answers
   fails then, one line naming the wait and the missing acknowledge.
2. APP_ID 0x00: 0x80 = bootloader -> download the image; 0x03 = the application already runs (no power loss since
   the last download) -> stop it (0xFF) in case a previous session left it measuring; anything else is an error.
   Then the zone mode: TMF8828_MODE 0x10 reads 0x00 in 3x3 mode (its reset value; every TMF8820/21 image) and 0x08
   in a TMF8828's 8x8 mode, which the application keeps while powered. Unless it reads 0x00, command 0x65 (switch to
   3x3 / 3x6 / 4x4 mode) is sent and 0x10 must then read 0x00, as ams' Linux driver switches it back; otherwise the
   start fails (an 8x8 capture is four time-multiplexed sub-captures, not one 3x3 frame).
3. Download: bootloader frames written to 0x08 with `i2c_rdwr` (up to 131 bytes, beyond SMBus's 32): DOWNLOAD_INIT
   0x14 with seed 0x29 (ams' C host driver sends it for its encrypted images; ams' own Python and Arduino drivers
   do not, and the bootloader takes either), SET_ADDR, then W_RAM chunks of <= 128 bytes. After each, the bootloader
   status `[status, size, checksum]` at 0x08 is polled while status >= 0x10 (busy: the register echoes the command
   it runs, 0x43, 0x41, ...) and must then read 0x00.
   RAMREMAP is not answered (the CPU restarts into the application): wait SETTLE_S, then poll APP_ID until 0x03.
4. Accuracy mode, as ams' Linux driver switches it: ACTIVE_RANGE 0x19 reads 0x6E (short-range high accuracy), 0x6F
   (long range, the default) or 0x00 (an application image without accuracy modes). Unless it reads 0x6E, CMD_STAT
   0x08 <- 0x6E, then ACTIVE_RANGE is read again and must read 0x6E: otherwise the start fails with one line naming
   both (the `tmf8820` sensor model describes short-range histograms only; long-range ones stored under it would put
   every surface in the wrong place), before anything is measured. ACTIVE_RANGE alone decides: it says the mode the
   model needs, whatever status the command answered (one other than 0x00 is logged).
5. Configure: 0x16 (load the common config page; 0x20 then reads 0x16), period ms 0x24 (u16 LE), kilo-iterations
   0x26 (u16 LE), POWER_CFG 0x33 with every field ams names cleared (their reset values: no timed standby between
   measurements; the bits it does not name are kept as read), SPAD map 0x34, ALG_SETTING_0 0x35 = 0x04, HIST_DUMP
   0x39 = 1 (raw histograms), then 0x15 (write config). After each command
   CMD_STAT echoes the command while busy (>= 0x10), then reads its status. ams' Linux driver takes 0x00 (ok) or 0x01
   (accepted) after any command, and so does the daemon; ams' Python driver expects 0x01 for measure and 0x00 for
   the others, so a 0x01 where it expects 0x00 is logged, once for each command. Anything else fails the start,
   the status named.
6. Interrupts: INT_STATUS 0xE1 <- 0xFF (write 1 to clear), then INT_ENAB 0xE2 |= result (0x02) and raw histogram
   (0x08) bits, as every reference does before measuring, and the error bit (0x40), as ams' Linux driver does (it
   enables all but "command done"); read-modify-write (the enables drive the INT pin), except that the "command done"
   enable (0x20) is cleared, as ams' Linux driver's enable clears it: commands are waited for on CMD_STAT (as every
   reference waits), the bit goes up after each command (measure included) and is never cleared while reading, so
   one enabled by another tool would hold the INT pin low for the whole measurement.
7. Measure: CMD_STAT <- 0x10 (accepted: 0x01).

Readout polls INT_STATUS: bit 0x08 = a histogram sub-packet waits at 0x20, bit 0x02 = a result (layouts in
`i2c_records`); bit 0x01 ("any interrupt has occurred") goes up with each of them and is cleared with each record,
as ams' Arduino driver clears it. CMD_STAT is checked before a frame's first record is read (ams' Linux driver checks
it before every message read; once per frame costs one register read instead of 31, ~3 % of the frame rate at
400 kHz), and again before the record after a refused or missing one. Each record is read in one `i2c_rdwr` transfer
and its bit cleared by writing it back. The TID is not waited for: ams' Linux driver re-reads 0x20 until the TID
changes because it clears the bit before it reads (so the bit of the last sub-packet it read is still set at its
next interrupt); read first and clear after, a record's bit goes up only once the chip has put a new record there.
A record that is not what its bit announces is refused (counted in bad_records, the last one's reason in
last_bad_record); a histogram sub-packet whose size field is not the documented one is taken (ams' drivers
do not check it) and counted in size_field_mismatches, with one warning in the log.
Bit 0x40 is the error interrupt ("one of the status registers has been set to a non-zero value", ams' Python
driver): at the poll that sees it the daemon clears it and reads CMD_STAT (which serves as the check of a record read
at the same poll) and the status registers 0x04-0x07. A CMD_STAT other than 0x00 / 0x01 (e.g. 0x03 "severe error,
stopped") means the application stopped measuring: a dropped link, named with the registers (the device boots,
downloads if needed, configures and measures again). With CMD_STAT still fine it is counted (error_interrupts, the
registers in last_error_interrupt) and logged once, and reading goes on, as ams' Linux driver goes on after logging
it (the register map does not say which status values raise it: a warning such as "no factory calibration" may).
The fallback, for a chip that stops without the interrupt: if no record arrives for `watchdog_s`, APP_ID and
CMD_STAT are checked: a sensor that lost power is back in its bootloader, and an application that stopped measuring
sends nothing more; either is a dropped link too. So is a CMD_STAT that still echoes a command (>= 0x10) after
`timeout_s` at any of these checks: the application hangs in that command (e.g. "CMD_STAT stuck at 0x10 (measure
still running)").
`stop` sends 0xFF and clears its INT_ENAB bits again.

`restart` (once the arm has settled) stops the measurement and starts a fresh one, as ams' Python driver's
stopMeasure/startMeasure and its Linux driver's stop/start do: 0xFF (status 0x00 or 0x01), INT_STATUS <- 0xFF (so
that no record of the stopped measurement is read), 0x10 (accepted: 0x01). The chip measures cyclically from the
0x10 on, so no record read after it was exposed before it.
"""

from __future__ import annotations

import errno
import logging
import time
from pathlib import Path
from typing import Callable

from spadscan.protocol.errors import DeviceError
from spadscan.protocol.sensor_model import SensorModel

from .device_node import I2C_GROUP, with_access_fix
from .firmware import FirmwareImage, download_frames, load_firmware
from .i2c_records import (HIST_RECORD, RESULT_RECORD, histogram_refusal, parse_histogram_record, parse_result_record,
                          result_refusal, size_field_disagreement)
from .tmf8820 import TMF8820
from .transport import RANGE_LONG, RANGE_NAMES, RANGE_NONE, RANGE_SHORT, LinkDown, Packet, Transport

log = logging.getLogger("spadscan.daemon")

REG_APP_ID, REG_APP_STATUS, REG_CMD_STAT, REG_ACTIVE_RANGE, REG_PAGE = 0x00, 0x04, 0x08, 0x19, 0x20
REG_ENABLE, REG_INT_STATUS, REG_INT_ENAB = 0xE0, 0xE1, 0xE2
REG_PERIOD, REG_KILO_ITER, REG_SPAD_MAP, REG_HIST_DUMP = 0x24, 0x26, 0x34, 0x39
REG_ALG_SETTING = 0x35
REG_TMF8828_MODE = 0x10
"""TMF8828_MODE (ams' register map, TMF8X2X_COM_TMF8828_MODE in ams' Linux driver): 0x00 3x3 / 3x6 / 4x4 mode, 0x08 a
TMF8828's 8x8 mode."""
MODE_3X3 = 0x00
REG_POWER_CFG = 0x33
POWER_CFG_FIELDS = 0x80 | 0x40 | 0x20 | 0x08 | 0x04
"""POWER_CFG's fields as ams' register map names them (TMF8X2X_COM_POWER_CFG in ams' Linux driver): goto_standby_timed
0x80, low_power_osc_on 0x40, keep_pll_running 0x20, allow_osc_retrim 0x08, pulse_interrupt 0x04, each reset 0.
Cleared at every start: the application keeps them while it stays powered, and one another tool set (timed standby
between measurements, a retrimmed oscillator) is not the chip the daemon's timing and sensor model describe."""
ALG_DISTANCES_ONLY = 0x04
"""ALG_SETTING_0 as ams documents its reset value: distances reported; no electrical calibration, statistics or
diagnostics records, the 5 m distance mode. Written at every start: the application keeps its configuration while
it stays powered, so a start after another tool (an Arduino sketch, ams' own GUI) finds whatever that tool set."""
ENABLE_PON, ENABLE_CPU_READY, ENABLE_CPU_RESET = 0x01, 0x40, 0x80
APP_BOOTLOADER, APP_RUNNING = 0x80, 0x03
CMD_MEASURE, CMD_STOP, CMD_LOAD_CONFIG, CMD_WRITE_CONFIG, CMD_SHORT_RANGE = 0x10, 0xFF, 0x16, 0x15, 0x6E
CMD_3X3_MODE = 0x65
"""CMD_SWITCH_TMF8821_MODE (ams' register map): to 3x3 / 3x6 / 4x4 mode; only images with 8x8 measurements take it."""
INT_ANY, INT_RESULT, INT_HISTOGRAM, INT_CMD_DONE, INT_ERROR = 0x01, 0x02, 0x08, 0x20, 0x40
"""INT_STATUS bits (ams' Python driver's TMF8X2X_APP_I2C_*_IRQ_MASK): 0x01 is "any of the others has occurred", 0x20
"a received I2C command has been handled (successfully or failed)"."""
INT_BITS = INT_RESULT | INT_HISTOGRAM | INT_ERROR
"""The INT_ENAB bits the daemon sets while measuring (and clears at stop)."""
REG_STATUS_NAMES = {0x04: "APPLICATION_STATUS", 0x05: "MEASURE_STATUS", 0x06: "ALGORITHM_STATUS",
                    0x07: "FACTORY_CALIBRATION_STATUS"}
"""The status registers the error interrupt is about (ams' register map)."""
BUSY = 0x10
"""CMD_STAT (bootloader and application) at or above this value: a command is still running."""
STAT_OK, STAT_ACCEPTED = 0x00, 0x01
"""CMD_STAT while the application measures: 0x01 (measure accepted, running until stopped), or 0x00 (ok), which
ams' Linux driver accepts too before it reads a record."""
STAT_NAMES = {0x00: "ok", 0x01: "accepted", 0x02: "configuration not accepted", 0x03: "application error, stopped",
              0x04: "wakeup timed, power cycle the device", 0x05: "unexpected reset, power cycle the device",
              0x06: "unknown command", 0x07: "no reference SPAD", 0x08: "no flicker SPAD",
              0x09: "unknown config page", 0x0E: "unknown mode"}
"""CMD_STAT values as ams' register map names them (0x0A-0x0D are warnings that a setting was ignored)."""
FRAME_START = "before a frame's first record"
"""When CMD_STAT is checked in the normal course of reading: once per frame (the `when` of `_require_measuring`)."""
SETTLE_S = 0.010
"""Wait after setting PON and after RAMREMAP before the chip is addressed again (the references wait 10 ms)."""
TIME_MULTIPLEXED_MAPS = frozenset({4, 5, 7, 10, 13, 15})
"""ams' predefined SPAD maps that take two sub-captures per result (4x4, 3x6, 8x8): not one 3x3 frame."""
PREDEFINED_MAPS = range(1, 14)
"""ams' predefined SPAD map ids (the config page's SPAD_MAP_ID, a 4-bit field): 14 is the user's own mask, which
needs the SPAD config page this driver never writes, and 15 the TMF8828's 8x8."""
BL_ERRORS = {0x01: "size error", 0x02: "checksum error", 0x03: "resource error", 0x04: "application error",
             0x05: "timeout", 0x06: "locked", 0x07: "address out of range", 0x08: "more data expected"}
COMMAND_NAMES = {CMD_MEASURE: "measure", CMD_STOP: "stop", CMD_LOAD_CONFIG: "load common config",
                 CMD_WRITE_CONFIG: "write config", CMD_SHORT_RANGE: "short-range mode", CMD_3X3_MODE: "3x3 mode"}
COMMAND_STATUS = (STAT_OK, STAT_ACCEPTED)
"""The statuses any command may answer: ams' Linux driver takes 0x00 (ok) or 0x01 (accepted) after every command."""
PYTHON_DRIVER_STATUS = {CMD_MEASURE: STAT_ACCEPTED}
"""The status ams' Python driver expects of a command (any other: 0x00); a 0x01 where it expects 0x00 is logged."""


class I2CTransport(Transport):
    """smbus2 link to a TMF8820 at `address` on `bus` (a number or a /dev/i2c-N path).

    smbus_factory(bus) returns an SMBus-like object (default `smbus2.SMBus`; tests pass the fake). Counters:
    records, bad_records (refused; last_bad_record says why the last one was), size_field_mismatches (histogram
    sub-packets taken although their size field is not the documented one), error_interrupts (error interrupts
    while the application went on measuring; the registers of the last one in last_error_interrupt), boots,
    downloads, and active_range (the accuracy mode the sensor measures in).
    """

    def __init__(self, bus: int | str, address: int = 0x41, firmware: Path | None = None, *, period_ms: int = 100,
                 kilo_iterations: int = 4000, spad_map: int = 1, smbus_factory: Callable | None = None,
                 poll_s: float = 0.002, timeout_s: float = 1.0, watchdog_s: float = 3.0):
        for key, v, hi in (("period_ms", period_ms, 0xFFFF), ("kilo_iterations", kilo_iterations, 0xFFFF),
                           ("spad_map", spad_map, 0xFF), ("address", address, 0x7F)):
            if not (isinstance(v, int) and 0 < v <= hi):
                raise DeviceError(f"i2c sensor: {key} = {v} must be an integer in [1, {hi}]")
        if spad_map not in PREDEFINED_MAPS and spad_map not in TIME_MULTIPLEXED_MAPS:
            raise DeviceError(f"i2c sensor: spad_map = {spad_map} is none of ams' predefined SPAD maps (1-13): the "
                              f"chip would measure with a mask the `tmf8820` sensor model does not describe; use 1")
        if spad_map in TIME_MULTIPLEXED_MAPS:
            raise DeviceError(f"i2c sensor: spad_map = {spad_map} is time-multiplexed (two sub-captures per result); "
                              "frames need one 3x3 capture: use SPAD map 1 (the `tmf8820` sensor model's)")
        self.bus_id, self.address = bus, address
        self.firmware_path = None if firmware is None else Path(firmware)
        self.period_ms, self.kilo_iterations, self.spad_map = period_ms, kilo_iterations, spad_map
        self.poll_s, self.timeout_s, self.watchdog_s = poll_s, timeout_s, watchdog_s
        self.period_s = period_ms / 1000  # the host reads each record itself: arrival_lag_s stays 0
        self.name = f"i2c bus {bus} addr {address:#04x}"
        self._factory = smbus_factory
        self._bus = None
        self._image: FirmwareImage | None = None
        self._last_record = 0.0
        self._check_before: str | None = FRAME_START  # why CMD_STAT is checked before the next record read (None: not)
        self._next_index: int | None = 0  # the sub-packet expected next (0 after a result; None after a refused one)
        self._statuses_noted: set[int] = set()  # commands that answered other than ams' Python driver expects: logged
        self._counts: dict[str, int | str] = {"records": 0, "bad_records": 0, "size_field_mismatches": 0,
                                              "error_interrupts": 0, "boots": 0, "downloads": 0}

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
            node = self.bus_id if isinstance(self.bus_id, str) else f"/dev/i2c-{self.bus_id}"  # smbus2 takes both
            raise LinkDown(with_access_fix(f"cannot open i2c bus {self.bus_id}: {exc}", exc, node, I2C_GROUP)) from None

    def start(self) -> None:
        self._counts["boots"] += 1
        self._power_on()
        app = self._read(REG_APP_ID)
        if app == APP_BOOTLOADER:
            self._download()
        elif app == APP_RUNNING:
            self._command(CMD_STOP)
        else:
            raise DeviceError(f"unexpected APP_ID {app:#04x} (expected {APP_BOOTLOADER:#04x} for the bootloader or "
                              f"{APP_RUNNING:#04x} for the application): is this a TMF8820?")
        self._zone_mode()  # first: a switch resets the application's configuration
        self._short_range_mode()
        self._command(CMD_LOAD_CONFIG)
        page = self._read(REG_PAGE)
        if page != CMD_LOAD_CONFIG:
            raise DeviceError(f"config page did not load: register 0x20 reads {page:#04x}, expected 0x16")
        self._block_write(REG_PERIOD, [self.period_ms & 0xFF, self.period_ms >> 8])
        self._block_write(REG_KILO_ITER, [self.kilo_iterations & 0xFF, self.kilo_iterations >> 8])
        self._write(REG_POWER_CFG, self._read(REG_POWER_CFG) & ~POWER_CFG_FIELDS)
        self._write(REG_SPAD_MAP, self.spad_map)
        self._write(REG_ALG_SETTING, ALG_DISTANCES_ONLY)
        self._write(REG_HIST_DUMP, 0x01)
        self._command(CMD_WRITE_CONFIG)
        self._write(REG_INT_STATUS, 0xFF)
        self._write(REG_INT_ENAB, self._read(REG_INT_ENAB) & ~INT_CMD_DONE | INT_BITS)
        self._measure()

    def restart(self) -> None:
        self._command(CMD_STOP)
        self._write(REG_INT_STATUS, 0xFF)  # a record of the stopped measurement still flagged is not read
        self._measure()

    def _measure(self) -> None:
        """Start measuring: the next record read begins a frame."""
        self._command(CMD_MEASURE)
        self._check_before, self._next_index = FRAME_START, 0
        self._last_record = time.monotonic()

    def stop(self) -> None:
        if self._bus is not None:
            self._command(CMD_STOP)
            self._write(REG_INT_ENAB, self._read(REG_INT_ENAB) & ~INT_BITS)

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
            if status & INT_ERROR:
                self._error_interrupt()
                self._check_before = None  # CMD_STAT was just read: the record below needs no second read
            if status & (INT_HISTOGRAM | INT_RESULT):
                pkt = self._take_record(status & INT_HISTOGRAM != 0)
                if pkt is not None:
                    return pkt
                continue
            now = time.monotonic()
            if now - self._last_record > self.watchdog_s:
                self._last_record = now
                self._check_measuring()
            if now >= deadline:
                return None
            time.sleep(min(self.poll_s, max(0.0, deadline - now)))

    def _take_record(self, histogram: bool) -> Packet | None:
        """Read the record waiting at 0x20 (a histogram sub-packet or a result) and clear its INT bit; the packet, or
        None when the record is refused (counted, with the reason)."""
        bit = INT_HISTOGRAM if histogram else INT_RESULT
        if self._check_before is not None:
            self._require_measuring(self._check_before)
            self._check_before = None
        buf = self._block_read(REG_PAGE, HIST_RECORD if histogram else RESULT_RECORD)
        t = time.monotonic()
        self._write(REG_INT_STATUS, bit | INT_ANY)  # nothing of this record stays flagged
        self._last_record = t
        pkt = (parse_histogram_record if histogram else parse_result_record)(buf, t)
        if pkt is None:
            self._counts["bad_records"] += 1
            kind, refusal = ("histogram sub-packet", histogram_refusal) if histogram else ("result", result_refusal)
            self._counts["last_bad_record"] = f"{kind}: {refusal(buf)}"
            self._check_before, self._next_index = "before the record after a refused one", None
            return None
        self._counts["records"] += 1
        if histogram:
            self._note_size_field(buf)
        self._note_sequence(pkt.index if histogram else None)
        return pkt

    def _note_sequence(self, index: int | None) -> None:
        """Keep track of where the frame is (`index`: the sub-packet just read, None for a result): CMD_STAT is checked
        before the next frame's first record, and before the next record when one was missed."""
        if index is None:
            self._check_before, self._next_index = FRAME_START, 0
            return
        if self._next_index is not None and index != self._next_index:
            self._check_before = "before the record after a missing one"
        self._next_index = index + 1

    def _note_size_field(self, buf: bytes) -> None:
        """Count a histogram sub-packet whose size field is not the documented one; warn about the first."""
        disagreement = size_field_disagreement(buf)
        if not disagreement:
            return
        self._counts["size_field_mismatches"] += 1
        if self._counts["size_field_mismatches"] == 1:
            log.warning("%s: histogram %s; the sub-packets are placed by their number all the same (the size field "
                        "is not needed for that), and such sub-packets are counted in size_field_mismatches",
                        self.name, disagreement)

    def _check_measuring(self) -> None:
        """After watchdog_s without a record: raise LinkDown (so the device boots and starts the sensor again) unless
        the application still runs and measures. The fallback for a chip that stops without raising its error
        interrupt (`_error_interrupt` catches the others at once).

        A power loss or reset puts the chip back in its bootloader (APP_ID). The application can also stop on its own
        while APP_ID stays 0x03: ams' register map has CMD_STAT 0x03 "severe error, stopped" (details in
        APPLICATION_STATUS 0x04) and 0x04 / 0x05 "power cycle the device"; while it measures CMD_STAT reads 0x01
        (measure accepted, runs until stopped), and ams' Linux driver takes 0x00 (ok) as well while it reads records;
        anything else means no record will ever come.
        """
        app = self._read(REG_APP_ID)
        if app != APP_RUNNING:
            raise LinkDown(f"sensor reset (APP_ID {app:#04x}, no record for {self.watchdog_s:g} s)")
        self._require_measuring(f"no record for {self.watchdog_s:g} s")

    def _require_measuring(self, when: str, registers: str | None = None) -> None:
        """Raise LinkDown unless CMD_STAT says the application measures (0x01 accepted, or 0x00 ok, as ams' Linux
        driver checks before a message read). A CMD_STAT that still echoes a command (>= 0x10) after timeout_s is an
        application hung in that command: a dropped link too, so that the device boots the sensor again. `when`
        says what led to the check and `registers` the status registers already read (default: APPLICATION_STATUS
        is read), for the message."""
        status, settled = self._read_settled()
        if settled and status in (STAT_OK, STAT_ACCEPTED):
            return
        if registers is None:
            registers = f"APPLICATION_STATUS {self._read(REG_APP_STATUS):#04x}"
        state = (f"CMD_STAT {status:#04x}{_stat_name(status)}" if settled else
                 f"CMD_STAT stuck at {status:#04x} ({_running(status)} still running) for {self.timeout_s:g} s")
        raise LinkDown(f"sensor stopped measuring ({state}, {registers}, {when})")

    def _error_interrupt(self) -> None:
        """INT_STATUS bit 0x40 is set: clear it, then LinkDown if the application stopped (CMD_STAT), else count it
        and warn once (the application measures on, as ams' Linux driver goes on after logging it)."""
        self._write(REG_INT_STATUS, INT_ERROR | INT_ANY)
        registers = ", ".join(f"{name} {self._read(reg):#04x}" for reg, name in REG_STATUS_NAMES.items())
        self._require_measuring("error interrupt: INT_STATUS bit 0x40", registers)
        self._counts["error_interrupts"] += 1
        self._counts["last_error_interrupt"] = registers
        if self._counts["error_interrupts"] == 1:
            log.warning("%s: the sensor raised its error interrupt (INT_STATUS bit 0x40: %s) and measures on; such "
                        "interrupts are counted in error_interrupts", self.name, registers)

    # ---- boot steps ----------------------------------------------------------------------------------------------
    def _power_on(self) -> None:
        enable = self._first_enable()
        if enable & (ENABLE_PON | ENABLE_CPU_READY) != ENABLE_PON | ENABLE_CPU_READY:
            self._write(REG_ENABLE, (enable | ENABLE_PON) & ~(ENABLE_CPU_RESET | ENABLE_CPU_READY))
            time.sleep(SETTLE_S)
        self._wait_waking(lambda: self._read(REG_ENABLE) & ENABLE_CPU_READY, "cpu_ready (ENABLE bit 6) after power-on")

    def _first_enable(self) -> int:
        """ENABLE as the chip first answers it. PON resets to 1, so a chip whose power just came (a replug, a power
        loss) starts its CPU by itself and acknowledges nothing meanwhile, this read included: a missing acknowledge
        means "still starting", as ams' Linux driver takes it (it sleeps 10 ms, then reads ENABLE up to 10 times,
        waking the chip again after each read not acknowledged). The bound is timeout_s (1 s by default), the one the
        CPU start after PON and after RAMREMAP already has, as this is the same start; a count of reads would last
        what the bus clock makes it. A sensor not wired, powered or at this address never answers: LinkDown after
        timeout_s, one line naming the wait and the missing acknowledge."""
        enable = 0

        def answered() -> bool:
            nonlocal enable
            enable = self._read(REG_ENABLE)
            return True

        self._wait_waking(answered, f"the sensor to answer (ENABLE {REG_ENABLE:#04x})")
        return enable

    def _download(self) -> None:
        if self._image is None:
            raise DeviceError("the sensor is in its bootloader and needs the firmware image: set the path to your "
                              "copy of the ams TMF8820 application image (firmware = PATH)")
        self._counts["downloads"] += 1
        for label, frame in download_frames(self._image):
            self._rdwr_write(bytes([REG_CMD_STAT]) + frame)
            if label != "RAMREMAP":
                self._bootloader_ok(label)
        time.sleep(SETTLE_S)
        self._wait_waking(lambda: self._read(REG_APP_ID) == APP_RUNNING,
                          f"the application to start after the download of {self._image.path} (APP_ID 0x03)")

    def _bootloader_ok(self, label: str) -> None:
        def ready():
            status, size, csum = self._block_read(REG_CMD_STAT, 3)
            if status >= BUSY:
                return False  # the bootloader still runs the command (the register echoes it)
            if csum != ~(status + size) & 0xFF:
                return False  # a garbled status read: read it again
            if status != 0x00:
                raise DeviceError(f"bootloader rejected {label}: {BL_ERRORS.get(status, 'error')} "
                                  f"(status {status:#04x})")
            return True

        self._wait(ready, f"the bootloader to accept {label}")

    def _zone_mode(self) -> None:
        """Leave a TMF8828's 8x8 mode (another tool may have left the application in it) for 3x3 mode, as ams' Linux
        driver switches it: command 0x65 unless TMF8828_MODE reads 0x00, then it must read 0x00."""
        mode = self._read(REG_TMF8828_MODE)
        if mode == MODE_3X3:
            return
        self._command(CMD_3X3_MODE)
        after = self._read(REG_TMF8828_MODE)
        if after != MODE_3X3:
            raise DeviceError(f"the sensor did not leave 8x8 mode: TMF8828_MODE 0x10 read {mode:#04x}, and "
                              f"{after:#04x} after command 0x65 (3x3 mode); frames need one 3x3 capture")
        log.info("%s: the sensor was in 8x8 mode (TMF8828_MODE %#04x); switched to 3x3 mode", self.name, mode)

    def _short_range_mode(self) -> None:
        """Switch to short-range high-accuracy mode as ams' Linux driver does (command 0x6E unless ACTIVE_RANGE reads
        0x6E, then ACTIVE_RANGE must read 0x6E); record the mode. A sensor that does not switch fails the start: the
        `tmf8820` sensor model describes short-range histograms, and long-range ones stored under it would misplace
        every surface."""
        mode = self._read(REG_ACTIVE_RANGE)
        if mode == RANGE_SHORT:
            self._counts["active_range"] = RANGE_NAMES[mode]
            return
        status = self._send(CMD_SHORT_RANGE)
        mode = self._read(REG_ACTIVE_RANGE)
        self._counts["active_range"] = RANGE_NAMES.get(mode, f"unknown ({mode:#04x})")
        if mode != RANGE_SHORT:
            raise DeviceError(short_range_refusal(status, mode))
        if status != STAT_OK:  # ACTIVE_RANGE decides: the mode the model needs is set
            self._note_status(CMD_SHORT_RANGE, status, "ACTIVE_RANGE reads 0x6e (short range), which decides")

    def _command(self, cmd: int) -> None:
        """Send an application command and require a status ams' Linux driver takes (`COMMAND_STATUS`); one that
        ams' Python driver would not take is logged (`_note_status`)."""
        status = self._send(cmd)
        if status not in COMMAND_STATUS:
            wanted = " or ".join(f"{s:#04x}{_stat_name(s)}" for s in COMMAND_STATUS)
            raise DeviceError(f"command {cmd:#04x} ({COMMAND_NAMES[cmd]}) answered status {status:#04x}"
                              f"{_stat_name(status)}, expected {wanted}")
        if status == STAT_ACCEPTED and PYTHON_DRIVER_STATUS.get(cmd, STAT_OK) == STAT_OK:
            self._note_status(cmd, status, "taken, as ams' Linux driver takes 0x00 or 0x01 after any command")

    def _note_status(self, cmd: int, status: int, why: str) -> None:
        """Log, once per command and transport, a command status other than the 0x00 ams' Python driver expects, and
        why it is taken: a config command's note must not hide the short-range switch's, nor the other way round."""
        if cmd in self._statuses_noted:
            return
        self._statuses_noted.add(cmd)
        log.warning("%s: command %#04x (%s) answered status %#04x%s where ams' Python driver expects 0x00 (ok); %s "
                    "(said once)", self.name, cmd, COMMAND_NAMES[cmd], status, _stat_name(status), why)

    def _send(self, cmd: int) -> int:
        """Write an application command to CMD_STAT and return its status once it no longer runs."""
        self._write(REG_CMD_STAT, cmd)
        return self._settled_status(f"command {cmd:#04x} ({COMMAND_NAMES[cmd]})")

    def _settled_status(self, what: str) -> int:
        """CMD_STAT once the command `what` no longer runs; DeviceError when it still runs after timeout_s."""
        status, settled = self._read_settled()
        if not settled:
            raise DeviceError(f"timed out after {self.timeout_s:g} s waiting for {what}")
        return status

    def _read_settled(self) -> tuple[int, bool]:
        """(CMD_STAT, whether it settled): polled while a command runs (the register echoes it, >= 0x10; ams' Linux
        driver waits the same way before it reads a record) for up to timeout_s; the last value read when it did not
        settle."""
        status = BUSY

        def done():
            nonlocal status
            status = self._read(REG_CMD_STAT)
            return status < BUSY

        settled = self._poll(done)  # sets `status`
        return status, settled

    def _wait_waking(self, ready: Callable[[], bool], what: str) -> None:
        """`_wait` while the chip's CPU starts (after PON, after RAMREMAP): it may acknowledge nothing for a while, and
        the 10 ms the references sleep first is no bound on that (ams' Linux driver wakes it again and retries the
        read, its Python driver polls on): a missing acknowledge means "not yet" until the timeout."""
        silent: LinkDown | None = None

        def answered() -> bool:
            nonlocal silent
            try:
                done = ready()
            except LinkDown as exc:
                silent = exc
                return False
            silent = None
            return done

        try:
            self._wait(answered, what)
        except DeviceError as exc:
            if silent is None:
                raise
            raise LinkDown(f"{exc}: {silent}") from None

    def _wait(self, ready: Callable[[], bool], what: str) -> None:
        if not self._poll(ready):
            raise DeviceError(f"timed out after {self.timeout_s:g} s waiting for {what}")

    def _poll(self, ready: Callable[[], bool]) -> bool:
        """Call `ready` every poll_s until it returns True (then True) or timeout_s has passed (then False)."""
        deadline = time.monotonic() + self.timeout_s
        while not ready():
            if time.monotonic() >= deadline:
                return False
            time.sleep(self.poll_s)
        return True

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


def _stat_name(status: int) -> str:
    """' (name)' of a CMD_STAT value as ams' register map names it, '' for a value it does not name."""
    name = STAT_NAMES.get(status)
    return f" ({name})" if name else ""


def _running(echo: int) -> str:
    """The command a busy CMD_STAT (>= 0x10) echoes, in words: 'measure', or 'command 0x43' for one not named."""
    return COMMAND_NAMES.get(echo, f"command {echo:#04x}")


def short_range_refusal(status: int, mode: int) -> str:
    """The one-line error of a sensor that did not switch to short range: what command 0x6E answered, what
    ACTIVE_RANGE reads, and what to do."""
    what = {RANGE_NONE: "an application image without accuracy modes", RANGE_LONG: "still long range",
            RANGE_SHORT: "short range"}.get(mode, "no accuracy mode ams documents")
    head = (f"the sensor did not switch to short-range high-accuracy mode: command 0x6e answered status "
            f"{status:#04x}{_stat_name(status)} and ACTIVE_RANGE 0x19 reads {mode:#04x} ({what})")
    if mode == RANGE_SHORT:  # the mode the model needs: no image to change (the start does not refuse it)
        return head
    return (f"{head}; the tmf8820 sensor model describes short-range histograms only, so nothing is measured: set "
            f"firmware = PATH to an ams TMF8820 application image with accuracy modes (short_range_accuracy), then "
            f"power-cycle the sensor")


def _bus_error(what: str, exc: OSError) -> LinkDown:
    """A failed transfer as a dropped link; a missing acknowledge says what to check."""
    if exc.errno in (errno.EREMOTEIO, errno.ENXIO, errno.EIO):
        return LinkDown(f"i2c {what}: no acknowledge (is the sensor wired, powered and at this address?)")
    return LinkDown(f"i2c {what} failed: {exc}")


class I2CSensor(TMF8820):
    """A TMF8820 on I2C `bus` at `address`; `firmware` is the path to the user's copy of the application image.

    period_ms: measurement period, ms; kilo_iterations: laser cycles per measurement in units of 1024 (ams' register
    0x26; 4000 ~ the ~4 M cycles the `tmf8820` model was fitted with); spad_map: ams' SPAD map id, one that is not
    time-multiplexed (1 is the `tmf8820` model's). firmware_notes/modes.md explains each.
    """

    def __init__(self, bus: int | str, address: int = 0x41, firmware: Path | None = None, *,
                 model: SensorModel | None = None, period_ms: int = 100, kilo_iterations: int = 4000,
                 spad_map: int = 1, smbus_factory: Callable | None = None, frame_timeout_s: float = 2.0,
                 link_grace_s: float = 5.0, timeout_s: float = 1.0, queue_frames: int = 256):
        transport = I2CTransport(bus, address, firmware, period_ms=period_ms, kilo_iterations=kilo_iterations,
                                 spad_map=spad_map, smbus_factory=smbus_factory, timeout_s=timeout_s)
        super().__init__(transport, model=model, frame_timeout_s=frame_timeout_s, link_grace_s=link_grace_s,
                         queue_frames=queue_frames)
