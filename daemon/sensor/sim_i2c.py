"""A register-level fake of the TMF8820 behind an object that quacks like `smbus2.SMBus`.

It answers `write_byte_data`, `read_byte_data`, `write_i2c_block_data` / `read_i2c_block_data` (32 bytes at most,
as smbus2) and `i2c_rdwr` with `smbus2.i2c_msg` messages. What it models, as ams' drivers and register map describe
the chip (misuse is answered as the chip would - an error status, an ignored write, a missing acknowledge - and
recorded in `violations`):

- ENABLE 0xE0: PON (bit 0), power-up select (bits 4:5, kept as written; RAMREMAP sets 2, "start the application in
  RAM"), standby (bit 1, read only: set while PON is 0, as ams' Python driver checks after a power-down), cpu_ready
  (bit 6). Setting PON wakes the CPU: for `startup_s` (5 ms by default) the chip acknowledges nothing, then cpu_ready
  shows after `ready_after_polls` reads of ENABLE; until then only ENABLE answers. The references sleep 10 ms first
  and then retry a read that is not acknowledged (ams' Linux driver wakes the chip again, its Python driver polls on):
  such reads are counted (`nacked_while_starting`), not misuse. The CPU starts what power-up select says: 2 restarts
  the application kept in RAM through a standby (PON cleared), anything else the bootloader. Power coming (`replug`,
  `power_cycle`) is a start too: PON is 1 at reset (ams' register map, as ams' Arduino driver defines it:
  TMF8828_ENABLE__pon__RESET 1), so the chip boots its bootloader by itself and reads 0x41 once it is ready, nothing
  acknowledged for `startup_s` first. A new fake is a chip whose power came before the test: PON 1, no silent window,
  cpu_ready after `ready_after_polls` reads of ENABLE.
- The bootloader (APP_ID 0x80) checks every frame's length and checksum; while it runs a command (`busy_polls`
  status reads) the status register echoes that command (0x43, 0x41, ...), then reads 0x00 or an error. RAMREMAP
  is not answered: after checking that every byte of the expected image arrived it restarts into the application
  (again no acknowledge for `startup_s`).
- The application (APP_ID 0x03): CMD_STAT echoes a command while it runs (`busy_polls` reads), then its status, as
  ams' Python driver expects it: 0x01 (accepted, runs until stopped) for measure 0x10 (`measure_stat`; ams' Linux
  driver takes 0x00 there too), 0x00 (ok) for every other command, or an error (0x02 config, 0x06 unknown command).
  ACTIVE_RANGE 0x19 reads 0x6F (long range) after the start and 0x6E after command 0x6E. An application image without
  accuracy modes (`accuracy_modes=False`) reads 0x00 there (the register map's "no active range supported"), stays
  so, and refuses 0x6E with 0x06: the register map says the command is "only supported if short_range_accuracy =
  1" but not which status an image without it answers; 0x06 "unknown command" is this fake's choice. Config
  registers take writes only while the common page (0x16) is loaded; 0x15 writes it. Measuring needs neither 0x6E nor
  a written config (the chip measures with its defaults). POWER_CFG 0x33 is kept with the configuration (reset 0x00:
  every field ams' register map names - goto_standby_timed 0x80, low_power_osc_on 0x40, keep_pll_running 0x20,
  allow_osc_retrim 0x08, pulse_interrupt 0x04 - resets to 0, TMF8X2X_COM_POWER_CFG in ams' Linux driver).
- A TMF8828 (`tmf8828=True`: an image built with 8x8_measurements) has TMF8828_MODE 0x10: 0x00 in 3x3 / 3x6 / 4x4
  mode (its reset value, what the application starts in), 0x08 in 8x8 mode. Command 0x6C switches to 8x8 mode and
  0x65 back; after either the device "will need to be re-configured" (ams' register map; ams' Linux driver calls
  the switch a device reset and resets the TID it keeps), so the configuration goes back to its reset values (8x8
  mode: SPAD map 15, the only one it takes) and the TID counter starts again. Without 8x8 measurements 0x10 reads
  0x00 and both commands answer 0x06 ("only supported if 8x8_measurements = 1"; which status is this fake's choice).
- INT_STATUS 0xE1 shows the bit of the record waiting at 0x20 (0x08 histogram sub-packet, 0x02 result) whether or not
  it is enabled; INT_ENAB 0xE2 only decides whether the INT pin is pulled low (`int_pin_low`). Writing 1 clears a bit.
  Bit 0x01 is "any of the other interrupts has occurred" (ams' Python driver's TMF8X2X_APP_I2C_ANY_IRQ_MASK): set
  with every record published and with the error interrupt, and kept until the host clears it (ams' Arduino driver
  clears it with every record, its Linux driver writes back every bit it read).
  Bit 0x40 is the error interrupt (ams' Python driver: "one of the <status> registers has been set to a non-zero
  value"; its Linux driver logs it, and checks CMD_STAT before it reads a record): the fake raises it when the
  application stops on an error (`stop_measuring`) and it stays set until the host clears it.
  Bit 0x20 is "command done" (ams' Python driver's TMF8X2X_APP_I2C_CMD_DONE_IRQ_MASK: "a received I2C command has been
  handled (successfully or failed)"; F_CMD_DONE_IRQ in ams' Linux driver, which enables every interrupt but this one
  and clears it with the others it read): it goes up, with bit 0x01, when an application command is handled, whatever
  its status - here when CMD_STAT stops echoing it (`busy_polls` reads; at once with none) - and stays set until the
  host clears it. An application hung in a command never raises it. ams' drivers wait for a command on CMD_STAT, not
  on this bit.
- A result (`frame_records`) is laid out as ams' drivers decode it: temperature an unsigned byte (the fake draws
  20-60 C), slot k the target (k // 18) + 1 of channel (k % 9) + 1 in sub-capture (k // 9) % 2. The fake measures
  with one SPAD map (no time multiplexing), so slots 0-8 hold each zone's first target, 18-26 its second (behind the
  first), 9-17 and 27-35 stay 0, and the valid-results count is the number of slots with a non-zero confidence.

Timing, as ams' drivers use the chip. The chip measures on its own clock: one measurement every `frame_interval_s`
(0: back to back, as fast as the readout frees its buffer), whether or not the host keeps up. A measured frame waits
in a one-frame buffer while the previous one is handed over; a newer measurement replaces it (`lost` counts those).
The frame's records (30 histogram sub-packets when HIST_DUMP bit 0 is set, then a result, laid out as `i2c_records`
describes) are handed over one at a time: the chip publishes the next record `handover_s` after the host clears the
INT bit of the one at 0x20, and until then 0x20 still holds the cleared record. ams' Python and Arduino drivers clear
the bit *before* they read the record, and ams' Linux driver clears it and then re-reads 0x20 until the TID changes,
so both orders must work and the hand-over is neither instant nor long. `hold_s` (None: wait for the host) is how
long the chip waits for a clear before it abandons the rest of that frame and goes on with the next measurement; the
frames it tore are listed in `torn`. The one-frame buffer and `hold_s` are this fake's assumptions: ams' drivers do not
say what a chip does with a host that falls behind, only that the chip does not wait for it to measure.

What it measured is kept in `produced` (its result number counts lost measurements too), and when each measurement
was exposed in `exposures` (monotonic (begin, end) s, same order): measuring cyclically, as ams' register map says of
the measure command 0x10, measurement j after a 0x10 at T is exposed over [T + j I, T + (j + 1) I] with
I = `frame_interval_s` (each takes its whole period, the longest it can take); back to back (I = 0) a measurement is
an instant, when the buffer frees. A stop (0xFF) ends the measurement: nothing measured before it is handed over
after it, but the record at 0x20 whose INT bit is up stays flagged until the host clears it (`_stop_command`).
Faults: `unplug`/`replug` (every transfer NACKs; a replug is a power-up), `power_cycle` (power lost: back
to the bootloader, RAM lost), `crash` (the chip resets itself into the bootloader but keeps answering),
`stop_measuring` (the application reports a severe error and stops, APP_ID still 0x03, with or without the error
interrupt), `hang` (the application hangs in a command: CMD_STAT echoes it for good, until a power cycle),
`set_status` (status registers change while it measures on), `corrupt_next_record` (of one frame or of every frame),
`app_id` (a wrong chip), `ready_after_polls=None` (cpu_ready never comes).

The histogram size field: ams' protocol documents the message still to come (`size_field="remaining"`, 3840 in
sub-packet 0, 128 less in each after it), but no ams driver checks it after sub-packet 0, so a firmware that writes
it otherwise would go unnoticed by them: `size_field="total"` writes the whole message size, 3840, in every
sub-packet, so that the driver is tested against both.
"""

from __future__ import annotations

import ctypes
import errno
import threading
import time

import numpy as np

ENABLE, INT_STATUS, INT_ENAB, CMD_STAT, ACTIVE_RANGE, APP_ID, APP_STATUS = 0xE0, 0xE1, 0xE2, 0x08, 0x19, 0x00, 0x04
TMF8828_MODE = 0x10
INT_ANY, INT_CMD_DONE, INT_ERROR = 0x01, 0x20, 0x40
"""INT_STATUS / INT_ENAB bits: "any", command done and the error interrupt (ams' TMF8X2X_APP_I2C_*_IRQ_MASK)."""
START_RAM_APP = 2
"""ENABLE power-up select (bits 4:5) value: start the application in RAM."""
SIZE_FIELDS = ("remaining", "total")
"""What a histogram sub-packet's size field holds: the message still to come (documented), or the whole message."""


TEMPERATURE_RANGE_C = (20, 60)
"""What the fake's chip reports as its temperature, deg C: a plausible die temperature on a bench or an arm."""
FIRST_TARGET_P, SECOND_TARGET_P = 0.9, 0.3
"""How often a zone's result holds a first target, and a zone with one a second target too (the fake's choice)."""


def zone_targets(rng: np.random.Generator) -> tuple[list[int], list[int]]:
    """36 result slots (distances mm, confidences) as one SPAD map without time multiplexing fills them: slots 0-8
    the first target of channels 1-9, slots 18-26 a second target behind it, slots 9-17 and 27-35 (sub-capture 1)
    empty (0, 0)."""
    distances, confidences = [0] * 36, [0] * 36
    for zone in range(9):
        if rng.random() >= FIRST_TARGET_P:
            continue
        first = int(rng.integers(50, 4000))
        distances[zone], confidences[zone] = first, int(rng.integers(1, 256))
        if rng.random() < SECOND_TARGET_P:
            distances[18 + zone], confidences[18 + zone] = int(rng.integers(first + 1, 5000)), int(rng.integers(1, 256))
    return distances, confidences


def frame_records(counts: np.ndarray, result: dict, hist_dump: bool, next_tid,
                  size_field: str = "remaining", diagnostics: bool = False) -> list[tuple[int, bytes]]:
    """The (INT_STATUS bit, bytes) records of one frame: 30 raw histogram sub-packets (when `hist_dump`), a result.
    `size_field`: one of SIZE_FIELDS. `diagnostics`: the result's size field counts the 36 diagnostics bytes that
    follow its 36 results (the register map's 0xA4-0xC7)."""
    if not 0 <= result["temperature_c"] <= 255:
        raise ValueError(f"temperature {result['temperature_c']} C: the chip reports an unsigned byte, 0..255")
    records = []
    if hist_dump:
        for k in range(30):
            plane = ((counts[k % 10] >> (8 * (k // 10))) & 0xFF).astype(np.uint8).tobytes()
            # sub-packet headers excluded either way
            size = (30 - k) * 128 if size_field == "remaining" else 30 * 128
            records.append((0x08, bytes([0x81, next_tid(), size & 0xFF, size >> 8, k, 128, 0]) + plane))
    n_valid = sum(1 for c in result["confidences"] if c)  # the slots that hold a target
    head = bytearray([0x10, next_tid(), 128 + 36 * diagnostics, 0, result["result_no"], result["temperature_c"],
                      n_valid, 0])
    head += b"".join(int(v).to_bytes(4, "little") for v in (1000, 200_000, 50_000, result["systick"]))
    body = b"".join(bytes([c]) + int(d).to_bytes(2, "little")
                    for c, d in zip(result["confidences"], result["distances_mm"]))
    records.append((0x02, bytes(head + body) + bytes(36 * diagnostics)))
    return records


class SimTMF8820Bus:
    """The fake bus with one TMF8820 at `address`. `image`: the bytes the download must deliver (None: any)."""

    def __init__(self, *, address: int = 0x41, image: bytes | None = None, seed: int = 0, frame_interval_s=0.0,
                 ready_after_polls: int | None = 2, busy_polls: int = 1, app_id: int | None = None,
                 load_address: int = 0, accuracy_modes: bool = True, startup_s: float = 0.005,
                 handover_s: float = 0.001, hold_s: float | None = None, size_field: str = "remaining",
                 measure_stat: int = 0x01, result_diagnostics: bool = False, tmf8828: bool = False):
        if size_field not in SIZE_FIELDS:
            raise ValueError(f"size_field = {size_field!r} must be one of {SIZE_FIELDS}")
        self.size_field = size_field
        # Both of what ams' Linux driver accepts: CMD_STAT 0x01 (accepted) or 0x00 (ok) while measuring; a result
        # record followed by the 36 diagnostics bytes (its size field 164 instead of 128), as it is also while
        # ALG_SETTING_0's diagnostics bit (0x40) is set in the configuration.
        self.measure_stat, self.result_diagnostics = measure_stat, result_diagnostics
        self.address, self.image, self.load_address = address, image, load_address
        self.frame_interval_s, self.ready_after_polls, self.busy_polls = frame_interval_s, ready_after_polls, busy_polls
        self.handover_s, self.hold_s = handover_s, hold_s
        self.lost = 0  # measurements replaced in the buffer before the host got to them
        self.torn: list[int] = []  # indices into `produced` of frames abandoned part-way (the host overran hold_s)
        self.app_id_override = app_id
        self.accuracy_modes, self.startup_s = accuracy_modes, startup_s
        self.tmf8828 = tmf8828  # the image has 8x8_measurements: TMF8828_MODE and commands 0x65 / 0x6C
        self.garbled_status_reads = 0  # bootloader status reads still to come back with a bit flipped on the bus
        self.rng = np.random.default_rng(seed)
        self.produced: list[tuple[np.ndarray, dict]] = []
        self.exposures: list[tuple[float, float]] = []  # (begin, end) of each measurement in `produced`, monotonic s
        self.violations: list[str] = []
        self.nacked_while_starting = 0
        """Reads and writes not acknowledged because the CPU was still starting (PON or RAMREMAP < startup_s ago)."""
        self.commands: list[int] = []
        self.spoiled: list[int] = []  # indices into `produced` of frames sent with a corrupt record
        self.opened = 0
        self.closed = False
        self.plugged = True
        self._lock = threading.Lock()
        self._corrupt: dict[int, int | None] = {}  # record index -> frames still to spoil (None: every frame)
        self._power_on_reset()
        self.starting_until = 0.0  # powered before the test: the silent start is over, cpu_ready comes on ENABLE reads

    # ---- test hooks ----------------------------------------------------------------------------------------------
    def unplug(self) -> None:
        self.plugged = False

    def replug(self) -> None:
        """Plug back in: the chip powered down meanwhile, so it is in its bootloader again."""
        with self._lock:
            self._power_on_reset()
        self.plugged = True

    def power_cycle(self) -> None:
        with self._lock:
            self._power_on_reset()

    def crash(self) -> None:
        """The chip resets itself into the bootloader (power and cpu_ready stay): RAM and config are lost."""
        with self._lock:
            self._power_on_reset()
            self.ready_countdown, self.starting_until = 0, 0.0

    def stop_measuring(self, cmd_stat: int = 0x03, app_status: int = 0x04, error_interrupt: bool = True) -> None:
        """The application stops measuring on its own and says why: CMD_STAT 0x03 "severe error, stopped" (0x04 and
        0x05: "power cycle the device"), APPLICATION_STATUS 0x04 the detail (4: unexpected reset). APP_ID stays 0x03.
        It raises the error interrupt (INT_STATUS 0x40: a status register became non-zero) unless `error_interrupt`
        is False (a chip whose error goes unannounced: only the host's watchdog notices)."""
        with self._lock:
            self._stop_records()
            self.cmd_stat, self.app_status = cmd_stat, app_status
            self._raise_error(error_interrupt)

    def hang(self, command: int = 0x10) -> None:
        """The application hangs while it runs `command`: CMD_STAT echoes it (>= 0x10, "busy", as it does while any
        command runs) from now on, nothing more is measured or handed over, and commands written to CMD_STAT are
        not taken. APP_ID stays 0x03; only a power cycle (or unplug) ends it."""
        with self._lock:
            self._stop_records()
            self.hung, self.cmd_stat, self.cmd_busy = True, command, 0

    def set_status(self, *, cmd_stat: int | None = None, app_status: int | None = None,
                   error_interrupt: bool = False) -> None:
        """While the application goes on measuring (records keep coming), CMD_STAT and/or APPLICATION_STATUS change,
        with or without the error interrupt: a status warning the application measures on with, or a host check of
        CMD_STAT before a record read (ams' Linux driver's) put to the test."""
        with self._lock:
            self.cmd_stat = self.cmd_stat if cmd_stat is None else cmd_stat
            self.app_status = self.app_status if app_status is None else app_status
            self._raise_error(error_interrupt)

    def corrupt_next_record(self, k: int = 7, frames: int | None = 1) -> None:
        """Spoil the header (RID) of the k-th histogram record of each of the next `frames` frames made (None: of
        every frame from now on)."""
        with self._lock:
            self._corrupt[k] = frames

    def int_pin_low(self) -> bool:
        """The open-drain INT pin: pulled low while an INT_STATUS bit that is set is enabled in INT_ENAB."""
        with self._lock:
            self._advance()
            return bool(self._int_status() & self.int_enab)

    # ---- the smbus2.SMBus surface --------------------------------------------------------------------------------
    def __call__(self, bus):
        """Use the fake itself as the `smbus_factory`: opening the bus returns it."""
        self.opened += 1
        self.closed = False
        return self

    def close(self) -> None:
        self.closed = True

    def read_byte_data(self, i2c_addr: int, register: int, force=None) -> int:
        with self._lock:
            self._select(i2c_addr, register)
            return self._read(register, 1)[0]

    def write_byte_data(self, i2c_addr: int, register: int, value: int, force=None) -> None:
        with self._lock:
            self._select(i2c_addr, register)
            self._write(register, bytes([value & 0xFF]))

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int, force=None) -> list[int]:
        if length > 32:
            raise ValueError("Desired block length over 32 bytes")
        with self._lock:
            self._select(i2c_addr, register)
            return list(self._read(register, length))

    def write_i2c_block_data(self, i2c_addr: int, register: int, data, force=None) -> None:
        if len(data) > 32:
            raise ValueError("Data length cannot exceed 32 bytes")
        with self._lock:
            self._select(i2c_addr, register)
            self._write(register, bytes(data))

    def i2c_rdwr(self, *msgs) -> None:
        with self._lock:
            pointer = None
            for msg in msgs:
                if msg.flags & 0x0001:  # I2C_M_RD
                    self._select(msg.addr, pointer if pointer is not None else 0)
                    data = self._read(pointer or 0, msg.len)
                    ctypes.memmove(msg.buf, data, msg.len)
                    pointer = (pointer or 0) + msg.len
                else:
                    raw = bytes(msg)
                    self._select(msg.addr, raw[0] if raw else 0)
                    if raw:
                        pointer = raw[0]
                        if len(raw) > 1:
                            self._write(raw[0], raw[1:])

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ---- the chip ------------------------------------------------------------------------------------------------
    def _power_on_reset(self) -> None:
        """Power comes: every register at its reset value, PON 1 among them, so the CPU starts the bootloader."""
        self.pon = True
        self.powerup_select = 0
        self._start_cpu()  # sets starting_until: the monotonic time until which nothing is acknowledged
        self.app_running = self.app_in_ram = False
        self.ram = bytearray(0x10000)
        self.written = np.zeros(0x10000, bool)
        self.ram_ptr = 0
        self.download_seed: int | None = None
        """The seed of the last DOWNLOAD_INIT (0x14), None before one."""
        self.bl_status, self.bl_cmd, self.bl_busy = 0x00, 0x00, 0
        self.cmd_stat, self.cmd_busy, self.app_status = 0x00, 0, 0x00
        self.hung = False  # `hang`: CMD_STAT echoes a command for good, and no command is taken
        self.int_enab = 0x00
        self.error_irq = False  # INT_STATUS bit 0x40, set until the host clears it
        self.cmd_done_irq = False  # INT_STATUS bit 0x20: a command was handled since the host last cleared it
        self.any_irq = False  # INT_STATUS bit 0x01: another bit was raised since the host last cleared this one
        self.mode_8x8 = False  # TMF8828_MODE 0x10 reads 0x08 (8x8 mode) rather than 0x00
        self.page = bytearray(0x80)  # registers 0x20..0x9F
        self.active_range = 0x00
        self._reset_config()
        self._stop_records()

    def _reset_config(self) -> None:
        """The configuration at its reset values (at power-up and after a switch between 8x8 and 3x3 mode)."""
        self.config = {"period_ms": 33, "kilo_iterations": 537, "spad_map": 15 if self.mode_8x8 else 1,
                       "hist_dump": 0, "alg_setting_0": 0x04, "power_cfg": 0x00}  # ams' reset values
        self.config_loaded = False
        self.tid = 0

    def _stop_command(self) -> None:
        """The host's stop (0xFF): nothing more is measured, and what was measured but not yet handed over is dropped;
        a record handed over and not yet cleared stays flagged in INT_STATUS until the host clears its bit, and is
        what 0x20 holds when a measurement starts again. ams' register map says only that the stop aborts the
        measurement; all three of ams' drivers clear INT_STATUS themselves around a stop or the next start (the Linux
        one clears the bits of a record it then drops unread), and none says that the chip does."""
        flagged = self.records[:1] if self.records and self.cleared_t is None else []
        published, shown = self.published_t, self.shown
        self._stop_records()
        if flagged:
            self.records, self.published_t, self.shown = flagged, published, shown

    def _stop_records(self) -> None:
        """No measurement: nothing measured, nothing to hand over (0x20 shows the config page again)."""
        self.measuring = False
        self.buffered: tuple[int, list[tuple[int, bytes]]] | None = None  # (index in produced, records) measured
        self.records: list[tuple[int, bytes]] = []  # (INT_STATUS bit, bytes): records[0] is at 0x20
        self.frame_index = -1  # the index in `produced` of the frame being handed over
        self.published_t = 0.0  # when records[0] was put at 0x20
        self.cleared_t: float | None = None  # when the host cleared records[0]'s INT bit (None: not yet)
        self.shown: bytes | None = None  # what 0x20 holds while measuring
        self.measured = 0  # measurements made, lost ones included (the result number)
        self.next_frame_t = 0.0

    def _select(self, addr: int, register: int) -> None:
        if addr != self.address or not self.plugged:
            raise OSError(errno.EREMOTEIO, "Remote I/O error")  # nobody acknowledged the address
        if time.monotonic() < self.starting_until:
            self.nacked_while_starting += 1
            raise OSError(errno.EREMOTEIO, "Remote I/O error")
        if register != ENABLE and not self._cpu_ready():
            self.violations.append(f"access to register {register:#04x} before cpu_ready")
            raise OSError(errno.EREMOTEIO, "Remote I/O error")

    def _cpu_ready(self) -> bool:
        return self.pon and self.ready_countdown == 0

    def _start_cpu(self) -> None:
        """The CPU (re)starts: no acknowledge for startup_s, then cpu_ready after ready_after_polls reads."""
        self.starting_until = time.monotonic() + self.startup_s
        self.ready_countdown = self.ready_after_polls

    def _read(self, reg: int, n: int) -> bytes:
        if reg == ENABLE:
            if self.pon and self.ready_countdown:
                self.ready_countdown -= 1
            value = ((0x01 if self.pon else 0x02) | self.powerup_select << 4 | (0x40 if self._cpu_ready() else 0))
            return bytes([value]).ljust(n, b"\0")
        if reg == APP_ID:
            app = 0x03 if self.app_running else 0x80
            return bytes([self.app_id_override if self.app_id_override is not None else app]).ljust(n, b"\0")
        if reg == INT_STATUS:
            self._advance()
            return bytes([self._int_status()])
        if reg == INT_ENAB:
            return bytes([self.int_enab])
        if reg == CMD_STAT and not self.app_running:
            busy = self.bl_busy > 0
            status = self.bl_cmd if busy else self.bl_status  # busy: the command it runs is echoed
            self.bl_busy = max(0, self.bl_busy - 1)
            frame = bytes([status, 0, ~status & 0xFF])
            if self.garbled_status_reads and not busy:
                # A transport fault, not the bootloader's: a bit of the status flipped on the bus, its checksum
                # (~(status + size), ams' Linux driver's check) left as sent.
                self.garbled_status_reads -= 1
                frame = bytes([status ^ 0x01]) + frame[1:]
            return frame[:n].ljust(n, b"\0")
        if reg == CMD_STAT:
            status = self.commands[-1] if self.cmd_busy else self.cmd_stat
            if self.cmd_busy:
                self.cmd_busy -= 1
                if not self.cmd_busy:
                    self._command_done()
            return bytes([status]).ljust(n, b"\0")
        if reg == APP_STATUS:
            return bytes([self.app_status if self.app_running else 0]).ljust(n, b"\0")
        if reg == ACTIVE_RANGE:
            return bytes([self.active_range if self.app_running else 0]).ljust(n, b"\0")
        if reg == TMF8828_MODE:
            return bytes([0x08 if self.app_running and self.mode_8x8 else 0]).ljust(n, b"\0")
        if 0x20 <= reg < 0xA0 and self.app_running:
            self._advance()
            src = self.shown if self.measuring and self.shown is not None else bytes(self.page)
            off = reg - 0x20
            return src[off:off + n].ljust(n, b"\0")
        return bytes(n)

    def _write(self, reg: int, data: bytes) -> None:
        if reg == ENABLE:
            self._enable(data[0])
        elif reg == CMD_STAT and not self.app_running:
            self._bootloader(data)
        elif reg == CMD_STAT:
            self._command(data[0])
        elif reg == INT_STATUS:
            self._advance()
            if data[0] & self._record_bit():
                self.cleared_t = time.monotonic()
            if data[0] & INT_ERROR:
                self.error_irq = False
            if data[0] & INT_CMD_DONE:
                self.cmd_done_irq = False
            if data[0] & INT_ANY:
                self.any_irq = False
        elif reg == INT_ENAB:
            self.int_enab = data[0]
        elif 0x24 <= reg < 0xA0 and self.app_running:
            if not self.config_loaded:
                self.violations.append(f"config write at {reg:#04x} without a loaded config page (ignored)")
                return
            off = reg - 0x20
            self.page[off:off + len(data)] = data

    def _enable(self, value: int) -> None:
        self.powerup_select = (value >> 4) & 0x3
        on = bool(value & 0x01)
        if on and not self.pon:
            # Wake-up: the CPU starts the application kept in RAM when power-up select says so, else the bootloader.
            self.app_running = self.powerup_select == START_RAM_APP and self.app_in_ram
            self.bl_status, self.bl_busy = 0x00, 0
            self._start_cpu()
        elif self.pon and not on:  # standby: the CPU stops, RAM (and the application in it) stays
            self.ready_countdown = None
            self._stop_records()
        self.pon = on

    def _bootloader(self, frame: bytes) -> None:
        self.bl_busy, self.bl_cmd = self.busy_polls, frame[0] if frame else 0
        if len(frame) < 3 or frame[1] != len(frame) - 3:
            self.bl_status = 0x01
            self.violations.append(f"bootloader frame of {len(frame)} bytes has a wrong length field")
            return
        if ~sum(frame[:-1]) & 0xFF != frame[-1]:
            self.bl_status = 0x02
            self.violations.append("bootloader frame with a wrong checksum")
            return
        cmd, payload = frame[0], frame[2:-1]
        self.bl_status = 0x00
        if cmd == 0x14 and len(payload) == 1:  # DOWNLOAD_INIT: the seed of an encrypted image's download
            self.download_seed = payload[0]
        elif cmd == 0x43 and len(payload) == 2:
            self.ram_ptr = payload[0] | payload[1] << 8
        elif cmd == 0x41 and len(payload) <= 128:
            end = self.ram_ptr + len(payload)
            if end > len(self.ram):
                self.bl_status = 0x07
                return
            self.ram[self.ram_ptr:end] = payload
            self.written[self.ram_ptr:end] = True
            self.ram_ptr = end
        elif cmd == 0x11 and not payload:
            self._remap()
        else:
            self.bl_status = 0x01
            self.violations.append(f"unknown bootloader command {cmd:#04x} with {len(payload)} bytes")

    def _remap(self) -> None:
        if self.image is not None:
            lo, hi = self.load_address, self.load_address + len(self.image)
            missing = int((~self.written[lo:hi]).sum())
            wrong = sum(a != b for a, b in zip(self.ram[lo:hi], self.image))
            if missing or wrong:
                self.bl_status = 0x04
                self.violations.append(f"RAMREMAP with {missing} image bytes missing and {wrong} wrong")
                return
        self.app_running = self.app_in_ram = True
        self.powerup_select = START_RAM_APP
        self.active_range = 0x6F if self.accuracy_modes else 0x00
        self.cmd_stat, self.cmd_busy = 0x00, 0
        self._start_cpu()
        self.ready_countdown = 0

    def _command(self, cmd: int) -> None:
        self.commands.append(cmd)
        if self.hung:
            return  # the application takes nothing: CMD_STAT goes on echoing the command it hangs in
        self.cmd_busy = self.busy_polls
        ok = 0x00
        if cmd == 0x10:
            if self.measuring:
                self.violations.append("measure while measuring")
                ok = 0x02
            else:
                self.measuring, ok = True, self.measure_stat
                self.app_status = 0x00  # ams' register map: a new measurement clears the status registers
                self.next_frame_t = time.monotonic() + self.frame_interval_s
        elif cmd == 0xFF:
            self._stop_command()
        elif cmd in (0x6E, 0x6F, 0x16, 0x65, 0x6C) and self.measuring:
            self.violations.append(f"command {cmd:#04x} while measuring")
            ok = 0x02
        elif cmd in (0x6E, 0x6F):
            if self.accuracy_modes:
                self.active_range = cmd
            else:
                ok = 0x06  # unknown command: this firmware has no accuracy modes
        elif cmd in (0x65, 0x6C):
            if self.tmf8828:
                self.mode_8x8 = cmd == 0x6C
                self._reset_config()  # a switch resets the device: it must be configured again
            else:
                ok = 0x06  # unknown command: this image has no 8x8 measurements
        elif cmd == 0x16:
            self.page[:] = bytes(0x80)
            self.page[0], self.page[2] = 0x16, 0x7C
            self.page[4:6] = self.config["period_ms"].to_bytes(2, "little")
            self.page[6:8] = self.config["kilo_iterations"].to_bytes(2, "little")
            self.page[0x14], self.page[0x19] = self.config["spad_map"], self.config["hist_dump"]
            self.page[0x13], self.page[0x15] = self.config["power_cfg"], self.config["alg_setting_0"]
            self.config_loaded = True
        elif cmd == 0x15 and self.config_loaded:
            p = self.page
            self.config = {"period_ms": p[4] | p[5] << 8, "kilo_iterations": p[6] | p[7] << 8,
                           "spad_map": p[0x14], "hist_dump": p[0x19], "alg_setting_0": p[0x15],
                           "power_cfg": p[0x13]}
        elif cmd == 0x15:
            self.violations.append("write config without a loaded config page")
            ok = 0x02
        else:
            self.violations.append(f"unknown command {cmd:#04x}")
            ok = 0x06
        self.cmd_stat = ok
        if not self.cmd_busy:
            self._command_done()

    def _command_done(self) -> None:
        """The application has handled a command (CMD_STAT no longer echoes it): INT_STATUS bit 0x20, and 0x01."""
        self.cmd_done_irq = self.any_irq = True

    def _int_status(self) -> int:
        return (self._record_bit() | (INT_ERROR if self.error_irq else 0) | (INT_CMD_DONE if self.cmd_done_irq else 0)
                | (INT_ANY if self.any_irq else 0))

    def _raise_error(self, raised: bool) -> None:
        """Raise the error interrupt (and with it the "any" bit) when `raised`; a raised one stays."""
        if raised:
            self.error_irq = self.any_irq = True

    def _record_bit(self) -> int:
        """The INT_STATUS bit of the record waiting at 0x20 (0 when none waits, or the host cleared it)."""
        return self.records[0][0] if self.records and self.cleared_t is None else 0

    def _advance(self) -> None:
        """Bring the chip up to now: measurements on its own clock, then the hand-over of records."""
        if not self.measuring:
            return
        now = time.monotonic()
        if self.frame_interval_s > 0 and now >= self.next_frame_t:
            missed = int((now - self.next_frame_t) // self.frame_interval_s)  # measured meanwhile, never sent
            self.measured += missed
            self.lost += missed + (self.buffered is not None)
            end = self.next_frame_t + missed * self.frame_interval_s  # the latest measurement finished by now
            self.next_frame_t += (missed + 1) * self.frame_interval_s
            self.buffered = self._measure(end - self.frame_interval_s, end)
        elif self.frame_interval_s <= 0 and self.buffered is None:
            self.buffered = self._measure(now, now)
        if self.records and self.cleared_t is not None and now >= self.cleared_t + self.handover_s:
            self.records.pop(0)  # the host is done with it: the next record goes to 0x20
            self._publish(self.cleared_t + self.handover_s)
        elif (self.records and self.cleared_t is None and self.hold_s is not None
              and now > self.published_t + self.hold_s):
            self.torn.append(self.frame_index)  # the host overran: the chip gives up on this frame
            self.records = []
        if not self.records and self.buffered is not None:
            (self.frame_index, self.records), self.buffered = self.buffered, None
            self._publish(now)
            if self.frame_interval_s <= 0:
                self.buffered = self._measure(now, now)

    def _publish(self, t: float) -> None:
        self.published_t, self.cleared_t = t, None
        if self.records:
            self.shown = self.records[0][1]
            self.any_irq = True  # the record's bit goes up, and with it "any interrupt has occurred"

    def _measure(self, begin: float, end: float) -> tuple[int, list[tuple[int, bytes]]]:
        """One measurement exposed over [begin, end]: its counts and result are kept in `produced`, its exposure in
        `exposures`; returns (its index there, its records)."""
        counts = self.rng.integers(0, 1 << 24, (10, 128), dtype=np.int64)
        n = len(self.produced)
        distances, confidences = zone_targets(self.rng)
        low, high = TEMPERATURE_RANGE_C
        result = {"result_no": self.measured % 256, "temperature_c": int(self.rng.integers(low, high + 1)),
                  "n_valid": sum(1 for c in confidences if c), "systick": int(self.rng.integers(0, 2**32)),
                  "distances_mm": distances, "confidences": confidences}
        self.measured += 1
        self.produced.append((counts, result))
        self.exposures.append((begin, end))
        records = frame_records(counts, result, bool(self.config["hist_dump"] & 0x01), self._tid, self.size_field,
                                self.result_diagnostics or bool(self.config["alg_setting_0"] & 0x40))
        for k in sorted(self._corrupt):
            if k < len(records) - 1:
                bit, rec = records[k]
                records[k] = (bit, b"\x7f" + rec[1:])
                self.spoiled.append(n)
        self._corrupt = {k: None if left is None else left - 1 for k, left in self._corrupt.items()
                         if left is None or left > 1}
        return n, records

    def _tid(self) -> int:
        self.tid = (self.tid + 1) & 0xFF
        return self.tid
