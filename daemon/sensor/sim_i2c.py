"""A register-level fake of the TMF8820 behind an object that quacks like `smbus2.SMBus`.

It answers `write_byte_data`, `read_byte_data`, `write_i2c_block_data` / `read_i2c_block_data` (32 bytes at most,
as smbus2) and `i2c_rdwr` with `smbus2.i2c_msg` messages, and enforces the sequence documented in `i2c_bus`:
nothing but ENABLE answers before PON and cpu_ready; the bootloader checks every frame's length and checksum and, at
RAMREMAP, that every byte of the expected image arrived (else the application does not start); commands need the
application; config registers only take writes while the config page is loaded; measure needs a written config.
Misuse is answered as the chip would (error status, ignored write, NACK) and recorded in `violations`.

While measuring it makes one frame per `frame_interval_s`: 30 histogram records (when HIST_DUMP bit 0 is set) then
a result record, each raised in INT_STATUS until its bit is cleared. What it sent is kept in `produced`.
Faults: `unplug`/`replug` (every transfer NACKs), `power_cycle` (powered down: back to the bootloader, RAM lost),
`crash` (the chip resets itself into the bootloader but keeps answering),
`corrupt_next_record`, `app_id` (a wrong chip), `ready_after_polls=None` (cpu_ready never comes).
"""

from __future__ import annotations

import ctypes
import errno
import threading
import time

import numpy as np


class SimTMF8820Bus:
    """The fake bus with one TMF8820 at `address`. `image`: the bytes the download must deliver (None: any)."""

    def __init__(self, *, address: int = 0x41, image: bytes | None = None, seed: int = 0, frame_interval_s=0.0,
                 ready_after_polls: int | None = 2, busy_polls: int = 1, app_id: int | None = None,
                 load_address: int = 0):
        self.address, self.image, self.load_address = address, image, load_address
        self.frame_interval_s, self.ready_after_polls, self.busy_polls = frame_interval_s, ready_after_polls, busy_polls
        self.app_id_override = app_id
        self.rng = np.random.default_rng(seed)
        self.produced: list[tuple[np.ndarray, dict]] = []
        self.violations: list[str] = []
        self.commands: list[int] = []
        self.spoiled: list[int] = []  # indices into `produced` of frames sent with a corrupt record
        self.opened = 0
        self.closed = False
        self.plugged = True
        self._lock = threading.Lock()
        self._corrupt: set[int] = set()
        self._power_on_reset()

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
            self.pon, self.ready_countdown = True, 0

    def corrupt_next_record(self, k: int = 7) -> None:
        """Spoil the header of the k-th histogram record of the next frame made."""
        self._corrupt.add(k)

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
        self.pon = False
        self.ready_countdown = None
        self.app_running = False
        self.ram = bytearray(0x10000)
        self.written = np.zeros(0x10000, bool)
        self.ram_ptr = 0
        self.bl_status, self.bl_busy = 0x00, 0
        self.cmd_stat, self.cmd_busy = 0x00, 0
        self.page = bytearray(0x80)  # registers 0x20..0x9F
        self.config_loaded = self.config_written = self.short_range = self.measuring = False
        self.config = {"period_ms": 0, "kilo_iterations": 537, "spad_map": 6, "hist_dump": 0}
        self.records: list[tuple[int, bytes]] = []  # (INT_STATUS bit, record bytes) waiting for the host
        self.tid = 0
        self.next_frame_t = 0.0

    def _select(self, addr: int, register: int) -> None:
        if addr != self.address or not self.plugged:
            raise OSError(errno.EREMOTEIO, "Remote I/O error")  # nobody acknowledged the address
        if register != 0xE0 and not self._cpu_ready():
            self.violations.append(f"access to register {register:#04x} before cpu_ready")
            raise OSError(errno.EREMOTEIO, "Remote I/O error")

    def _cpu_ready(self) -> bool:
        return self.pon and self.ready_countdown == 0

    def _read(self, reg: int, n: int) -> bytes:
        if reg == 0xE0:
            if self.pon and self.ready_countdown:
                self.ready_countdown -= 1
            return bytes([(0x01 if self.pon else 0) | (0x40 if self._cpu_ready() else 0)])
        if reg == 0x00:
            app = 0x03 if self.app_running else 0x80
            return bytes([self.app_id_override if self.app_id_override is not None else app])
        if reg == 0xE1:
            self._make_frame()
            return bytes([self.records[0][0] if self.records else 0])
        if reg == 0x08 and not self.app_running:
            status = 0x10 if self.bl_busy else self.bl_status
            self.bl_busy = max(0, self.bl_busy - 1)
            return bytes([status, 0, ~status & 0xFF])[:n].ljust(n, b"\0")
        if reg == 0x08:
            status = self.commands[-1] if self.cmd_busy and self.commands else self.cmd_stat
            self.cmd_busy = max(0, self.cmd_busy - 1)
            return bytes([status]).ljust(n, b"\0")
        if 0x20 <= reg < 0xA0 and self.app_running:
            src = self.records[0][1] if self.measuring and self.records else bytes(self.page)
            off = reg - 0x20
            return src[off:off + n].ljust(n, b"\0")
        return bytes(n)

    def _write(self, reg: int, data: bytes) -> None:
        if reg == 0xE0:
            on = bool(data[0] & 0x01)
            if on and not self.pon:
                self.ready_countdown = self.ready_after_polls
            self.pon = on
            return
        if reg == 0x08 and not self.app_running:
            self._bootloader(data)
        elif reg == 0x08:
            self._command(data[0])
        elif reg == 0xE1:
            if self.records and data[0] & self.records[0][0]:
                self.records.pop(0)
        elif 0x24 <= reg < 0xA0 and self.app_running:
            if not self.config_loaded:
                self.violations.append(f"config write at {reg:#04x} without a loaded config page (ignored)")
                return
            off = reg - 0x20
            self.page[off:off + len(data)] = data

    def _bootloader(self, frame: bytes) -> None:
        self.bl_busy = self.busy_polls
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
        if cmd == 0x43 and len(payload) == 2:
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
        self.app_running = True
        self.cmd_stat, self.cmd_busy = 0x00, 0

    def _command(self, cmd: int) -> None:
        self.commands.append(cmd)
        self.cmd_busy = self.busy_polls
        ok = 0x00
        if cmd == 0x10:
            why = ("while measuring" if self.measuring else "before write config" if not self.config_written
                   else "without short-range mode (0x6E)" if not self.short_range else "")
            if why:
                self.violations.append(f"measure {why}")
                ok = 0x02
            else:
                self.measuring, ok = True, 0x01
                self.next_frame_t = time.monotonic() + self.frame_interval_s
        elif cmd == 0xFF:
            self.measuring, self.records = False, []
        elif cmd in (0x6E, 0x16) and self.measuring:
            self.violations.append(f"command {cmd:#04x} while measuring")
            ok = 0x02
        elif cmd == 0x6E:
            # A mode switch reloads the mode's defaults: a config written before it is gone.
            self.short_range, self.config_loaded, self.config_written = True, False, False
        elif cmd == 0x16:
            self.page[:] = bytes(0x80)
            self.page[0], self.page[2] = 0x16, 0x7C
            self.page[4:6] = self.config["period_ms"].to_bytes(2, "little")
            self.page[6:8] = self.config["kilo_iterations"].to_bytes(2, "little")
            self.page[0x14], self.page[0x19] = self.config["spad_map"], self.config["hist_dump"]
            self.config_loaded = True
        elif cmd == 0x15 and self.config_loaded:
            p = self.page
            self.config = {"period_ms": p[4] | p[5] << 8, "kilo_iterations": p[6] | p[7] << 8,
                           "spad_map": p[0x14], "hist_dump": p[0x19]}
            self.config_written = True
        else:
            self.violations.append(f"command {cmd:#04x} refused in this state")
            ok = 0x02
        self.cmd_stat = ok

    def _make_frame(self) -> None:
        """Queue the next frame's records when measuring, nothing is pending and its time has come."""
        now = time.monotonic()
        if not self.measuring or self.records or now < self.next_frame_t:
            return
        self.next_frame_t = max(now, self.next_frame_t + self.frame_interval_s)
        counts = self.rng.integers(0, 1 << 24, (10, 128), dtype=np.int64)
        n = len(self.produced)
        result = {"result_no": n % 256, "temperature_c": int(self.rng.integers(-20, 60)), "n_valid": 9,
                  "systick": int(self.rng.integers(0, 2**32)), "distances_mm": self.rng.integers(0, 5000, 36).tolist(),
                  "confidences": self.rng.integers(0, 256, 36).tolist()}
        self.produced.append((counts, result))
        if self.config["hist_dump"] & 0x01:
            for k in range(30):
                plane = ((counts[k % 10] >> (8 * (k // 10))) & 0xFF).astype(np.uint8).tobytes()
                rec = bytearray([0x81, self._tid(), 131, 0, k, 128, 0]) + plane
                if k in self._corrupt:
                    rec[0] = 0x7F
                    self.spoiled.append(n)
                self.records.append((0x08, bytes(rec)))
            self._corrupt.clear()
        head = bytearray([0x10, self._tid(), 128, 0, result["result_no"], result["temperature_c"] & 0xFF, 9, 0])
        head += b"".join(int(v).to_bytes(4, "little") for v in (1000, 200_000, 50_000, result["systick"]))
        body = b"".join(bytes([c]) + int(d).to_bytes(2, "little")
                        for c, d in zip(result["confidences"], result["distances_mm"]))
        self.records.append((0x02, bytes(head + body)))

    def _tid(self) -> int:
        self.tid = (self.tid + 1) & 0xFF
        return self.tid
