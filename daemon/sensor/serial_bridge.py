"""The TMF8820 behind an Arduino bridge that prints the sensor's records as text lines over USB serial (pyserial).

Line format (one record per line, fields separated by commas, `\\n` or `\\r\\n`; ams' Arduino driver, which the UW
firmware is built on, prints no trailing comma, and the UW consumer requires exactly 131 `#Raw` and 78 `#Obj` fields;
a trailing comma is tolerated all the same):

    #Raw,<i2c addr>,<sub-packet 0..29>,<128 byte values 0..255>          131 fields
    #Obj,<i2c addr>,<result no>,<temperature>,<n valid>,<systick>,
         <distance mm>,<confidence> x 36                                  78 fields
    #Obj                                                                  a separator, ignored
    #Err,<text...>   #Vers,<text...>                                      status lines

The temperature is the result record's byte, degrees C, printed as an unsigned number (0..255) and read so, as every
ams driver reads it. The valid-results count is the record's byte as printed; its bits 5:0 hold the count (the
register map's 6-bit field). With no checksum, a printed count over 36 marks a corrupt line (as a confidence over
255 does) unless bits 7:6 explain it: then its bits 5:0 must count the pairs that hold a target (a non-zero distance
or confidence, as ams' Linux driver counts them). The 36 distance/confidence pairs are the result slots
(`i2c_records`: slot k is target k // 18 + 1 of channel k % 9 + 1), their distances clock-corrected by the firmware
(ams' Arduino driver's tmf882xCorrectDistance, on by default in the UW firmware), unlike the I2C backend's raw ones.

`#Prt` lines (partial histograms: the UW consumer reads them as a "partial" histogram type, but no ams or UW source
says which bins they carry or what the field after their sub-packet number is) are refused with a line saying so: a
frame is 30 full `#Raw` sub-packets. The bridge has no checksum: a line is accepted when its tag, field count and
every value are well-formed and in range; anything else (a partial line after a mid-line start or an
unplug, two lines run together, line noise, another sensor's line) is refused and counted (in bad_records, as the I2C
transport counts its refused records, and by kind), and the frame it belonged to is dropped by the frame assembler.

The bridge's "Active range: <hex>" line (the ACTIVE_RANGE the firmware reads as it starts) must say 6E, short-range
high accuracy: in the other modes ams documents (6F long range, 0 an image without accuracy modes) the transport
refuses to go on (a DeviceError, which stops the device's reader before a frame of that mode is made), as the I2C
backend refuses to start, since the `tmf8820` sensor model describes short-range histograms only. The daemon cannot
switch the bridge's mode: its firmware must. Any other value is a garbled line (with no checksum, a dropped or
flipped character turns 6E into 6, E or 4E): refused and counted as a corrupt line, the mode left as it was.

Timing: the bridge keeps the sensor measuring on the period its firmware sets (the UW firmware: 230 ms) and cannot be
told to start a fresh measurement. In its loop it clears a record's interrupt, reads the record over I2C and prints
it; the chip hands over the next record after the clear. A frame's `t_start` counts back from the arrival of the line
before its first `#Raw` line by two periods and `arrival_lag_s` (`assembly.FrameAssembler` has the model).
"""

from __future__ import annotations

import collections
import logging
import re
import time

import serial

from spadscan.protocol.errors import DeviceError
from spadscan.protocol.sensor_model import SensorModel

from .device_node import SERIAL_GROUP, with_access_fix
from .i2c_records import valid_results
from .tmf8820 import TMF8820
from .transport import (N_RESULTS, N_SUBPACKETS, RANGE_LONG, RANGE_NAMES, RANGE_NONE, RANGE_SHORT, SUBPACKET_BYTES,
                        HistogramPacket, LinkDown, Packet, ResultPacket, StatusPacket, Transport)

log = logging.getLogger("spadscan.daemon")

RAW_FIELDS = 3 + SUBPACKET_BYTES
OBJ_FIELDS = 6 + 2 * N_RESULTS
MAX_LINE_BYTES = 4096
"""A line longer than this without a newline is garbage (a #Raw line is at most ~520 bytes)."""
LINE_EXCERPT_BYTES = 24
"""How much of a refused line its reason quotes: enough to tell a tag, a partial line or noise."""
BRIDGE_PERIOD_MS = 230
"""The measurement period the UW bridge firmware configures (its PERIOD), ms."""
BRIDGE_READ_AND_USB_S = 0.03
"""Bound on the time from the bridge's clear of a record's interrupt to the arrival of its line, printing aside, s:
reading the 132-byte result over I2C (~12 ms at 100 kHz, ~3 ms at the firmware's 400 kHz) and the USB link's
delivery (a USB-serial chip holds data up to its latency timer: 16 ms by default on FTDI chips)."""
PRINTED_BYTES = 1200
"""Bytes the bridge may print between a hand-over and the arrival the next frame counts back from: two lines."""
BRIDGE_START_S = 15.0
"""How long the UW bridge firmware may take from its "FW downloaded" line to its first record, s: it then sends the
short-range command and waits 4 s for it, runs a factory calibration (4,000 kilo-iterations), configures the sensor
and starts measuring (its "Active range" line comes then, the first record a period later). A frame wait that runs
out within this of that line is begun again (`starting_left`): a replug that powered the sensor off is a start, not
a silent sensor."""


def _uint(field: bytes, limit: int) -> int:
    """A decimal integer in [0, limit] (no signs, spaces or other bytes); otherwise a ValueError naming the field."""
    if not field.isdigit() or len(field) > 10 or int(field) > limit:
        raise ValueError(f"'{_printable(field, 12)}', not a decimal number in 0..{limit}")
    return int(field)


def _printable(data: bytes, limit: int) -> str:
    """The first `limit` bytes of `data` as one line of text: printable ASCII kept, other bytes as \\xNN."""
    text = "".join(chr(b) if 32 <= b < 127 else f"\\x{b:02x}" for b in data[:limit])
    return text + ("..." if len(data) > limit else "")


PARTIAL_HISTOGRAM = ("the bridge prints partial histograms (#Prt lines: its partial-histogram mode), whose bins the "
                     "daemon cannot place in a frame: flash or set the bridge firmware to dump full raw histograms "
                     "(HIST_DUMP raw, 30 #Raw lines of 128 bins per frame, as the UW firmware does)")
"""Why a `#Prt` line is refused, in one line for the operator."""


def classify_line(line: bytes, t: float, address: int | None) -> Packet | tuple[str, str]:
    """Decode one line (without its newline): a packet, or (kind, why) for a line that is skipped, kind one of
    'corrupt', 'separator', 'other_address', 'partial_histogram', 'unknown' and why in words for the operator ('' for
    a separator)."""
    line = line.rstrip(b"\r")
    note = _bridge_note(line, t)
    if note is not None:
        return note
    fields = line.split(b",")
    if len(fields) > 1 and fields[-1] == b"":
        fields.pop()  # the bridge ends some lines with a comma
    tag = fields[0]
    try:
        if tag == b"#Raw":
            return _raw_record(fields, t, address)
        if tag == b"#Obj":
            return ("separator", "") if len(fields) == 1 else _obj_record(fields, t, address)
        if tag == b"#Prt":
            return "partial_histogram", PARTIAL_HISTOGRAM
        if tag in (b"#Err", b"#Vers"):
            text = b",".join(fields[1:]).decode("ascii", "replace")
            return StatusPacket(kind="error" if tag == b"#Err" else "version", text=text, t=t)
    except ValueError as exc:
        return "corrupt", f"a {_printable(tag, 8)} line with {exc}"
    if not tag.startswith(b"#") or len(tag) > 8:
        return "corrupt", "a line without a '#' tag: part of a line, or noise (a baud rate other than the bridge's?)"
    if tag == b"#Cal":  # ams' shim prints electrical-calibration histograms under it (HIST_DUMP = 2)
        return "unknown", ("a #Cal line: electrical-calibration histograms, which the bridge firmware prints only when "
                           "set to dump them; it must dump raw histograms alone (HIST_DUMP = 1)")
    return "unknown", f"a {_printable(tag, 8)} line, a tag the bridge does not print"


def _raw_record(fields: list[bytes], t: float, address: int | None) -> HistogramPacket | tuple[str, str]:
    """A #Raw line's fields as a histogram sub-packet, or (kind, why); ValueError for a malformed value."""
    if len(fields) != RAW_FIELDS:
        return "corrupt", f"a #Raw line of {len(fields)} fields, not {RAW_FIELDS}"
    addr, index = _uint(fields[1], 127), _uint(fields[2], N_SUBPACKETS - 1)
    payload = bytes(_uint(f, 255) for f in fields[3:])
    if address is not None and addr != address:
        return "other_address", f"a #Raw line for I2C address {addr}, not {address}"
    return HistogramPacket(index=index, payload=payload, t=t)


def _obj_record(fields: list[bytes], t: float, address: int | None) -> ResultPacket | tuple[str, str]:
    """An #Obj line's fields (not a separator) as a result record, or (kind, why); ValueError for a malformed
    value."""
    if len(fields) != OBJ_FIELDS:
        return "corrupt", f"a #Obj line of {len(fields)} fields, not {OBJ_FIELDS}"
    addr = _uint(fields[1], 127)
    printed = _uint(fields[4], 255)
    pairs = [_uint(f, 65535) for f in fields[6:]]
    confidence = max(pairs[1::2])
    if confidence > 255:
        return "corrupt", f"a #Obj line with a confidence of {confidence}, more than a byte"
    refusal = valid_count_refusal(printed, pairs[0::2], pairs[1::2])
    if refusal:
        return "corrupt", f"a #Obj line with {refusal}"
    if address is not None and addr != address:
        return "other_address", f"a #Obj line for I2C address {addr}, not {address}"
    return ResultPacket(result_no=_uint(fields[2], 255), temperature_c=float(_uint(fields[3], 255)),
                        n_valid=valid_results(printed), systick=_uint(fields[5], 2**32 - 1),
                        distances_mm=pairs[0::2], confidences=pairs[1::2], t=t)


def valid_count_refusal(printed: int, distances: list[int], confidences: list[int]) -> str:
    """Why an #Obj line's printed valid-results count marks it corrupt, or '' when it does not. A count up to 36 is
    taken. The bridge has no checksum, so one over 36 is taken only where the register map's upper bits 7:6 explain
    it: its bits 5:0 must then count exactly the pairs that hold a target (ams' Linux driver counts a slot with a
    non-zero confidence or distance as one). Masking alone would let 111 of the values 37..255 through."""
    if printed <= N_RESULTS:
        return ""
    count, held = valid_results(printed), sum(1 for d, c in zip(distances, confidences) if d or c)
    if count == held:  # at most 36: bits 7:6 alone make the printed value larger
        return ""
    why = f"{printed} valid results, more than {N_RESULTS}"
    if count <= N_RESULTS:
        why += f" (its bits 5:0 read {count}, but {held} pairs hold a target)"
    return why


FIRMWARE_DOWNLOADED = b"FW downloaded"
ACTIVE_RANGE_LINE = re.compile(rb"Active range: ([0-9A-Fa-f]{1,2})")
BRIDGE_NOTES = ("firmware_downloaded", "active_range")
"""StatusPacket kinds of the lines the UW bridge prints without a '#' tag: after each download, and on every start
the sensor's ACTIVE_RANGE (hex, as Arduino's print(x, HEX) writes it)."""


def bridge_mode_refusal(mode: int, printed: str) -> str:
    """The one-line error of a bridge whose "Active range" line names a mode ams documents other than 6E (6F, 0):
    what it reports, and what to do."""
    what = {RANGE_LONG: "long range", RANGE_NONE: "an application image without accuracy modes"}.get(
        mode, "no accuracy mode ams documents")
    return (f"the bridge firmware runs the sensor in {what} (Active range: {printed}), not short-range high accuracy "
            f"(6E), the only mode the tmf8820 sensor model describes, so no frame is stored: the daemon cannot switch "
            f"the bridge's mode, so build and flash a bridge firmware that sets short-range high accuracy (command "
            f"0x6E after it downloads an ams application image with accuracy modes, before it measures, as the UW "
            f"firmware does), then reset the bridge and restart the daemon")


def _bridge_note(line: bytes, t: float) -> StatusPacket | None:
    """The bridge's own untagged status lines as packets (they are no line noise), else None."""
    text = line.strip()
    if text == FIRMWARE_DOWNLOADED:
        return StatusPacket(kind="firmware_downloaded", text=text.decode(), t=t)
    match = ACTIVE_RANGE_LINE.fullmatch(text)
    if match:
        return StatusPacket(kind="active_range", text=match.group(1).decode().upper(), t=t)
    return None


class SerialBridgeTransport(Transport):
    """pyserial link to the bridge: splits the byte stream into lines, timestamps and parses them.

    The port is reopened by path after an unplug (use a stable path such as /dev/serial/by-id/...). Counters:
    lines, corrupt_lines, unknown_lines, other_address_lines, partial_histogram_lines, separators, overlong_lines;
    bad_records, the lines refused (all of those but separators), with last_bad_record saying why the last one was and
    how it began; once
    the bridge has said so, downloads (its "FW downloaded" lines) and active_range (the accuracy mode its "Active
    range" line reports).
    """

    restarts_measurement = False  # the bridge measures on its own; a reopen restarts only boards reset by DTR
    error_hint = ("the UW bridge firmware stops measuring after a failed read and does not resume: reset or replug "
                  "the bridge")

    def __init__(self, port: str, baud: int = 1_000_000, address: int | None = 0x41,
                 period_ms: float = BRIDGE_PERIOD_MS):
        if not (isinstance(period_ms, (int, float)) and 0 < period_ms <= 65535):
            raise DeviceError(f"serial sensor: bridge period {period_ms} ms must be in (0, 65535] ms")
        self.port = str(port)
        self.baud = int(baud)
        self.address = address
        self.period_s = period_ms / 1000
        self.arrival_lag_s = BRIDGE_READ_AND_USB_S + PRINTED_BYTES * 10 / self.baud  # 10 bits a byte on the UART
        self.name = f"serial {self.port}"
        self._ser: serial.Serial | None = None
        self._buf = bytearray()
        self._pending: collections.deque[tuple[bytes, float]] = collections.deque()
        self._counts = {"lines": 0, "corrupt_lines": 0, "unknown_lines": 0, "other_address_lines": 0,
                        "partial_histogram_lines": 0, "separators": 0, "overlong_lines": 0, "bad_records": 0}
        self._downloaded_at: float | None = None  # arrival of a "FW downloaded" line with no record since

    def open(self) -> None:
        if self._ser is not None:
            return
        try:
            ser = serial.Serial(self.port, self.baud, timeout=0.05)
            ser.reset_input_buffer()  # bytes that waited in the OS buffer would get false arrival times
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkDown(with_access_fix(f"cannot open port at {self.baud} baud: {exc}", exc, self.port,
                                           SERIAL_GROUP)) from None
        self._ser = ser
        self._buf.clear()
        self._pending.clear()
        self._downloaded_at = None

    def start(self) -> None:
        """Empty the link: lines that waited in the OS buffer since `open` would get late arrival times, and a
        frame's t_start counts back from an arrival."""
        if self._ser is None:
            raise LinkDown("port is not open")
        try:
            self._ser.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise LinkDown(f"cannot empty the port's input: {exc}") from None
        self._buf.clear()
        self._pending.clear()

    def read_packet(self, timeout_s: float) -> Packet | None:
        deadline = time.monotonic() + timeout_s
        while True:
            while self._pending:
                line, t = self._pending.popleft()
                self._counts["lines"] += 1
                out = classify_line(line, t, self.address)
                if isinstance(out, StatusPacket) and out.kind in BRIDGE_NOTES:
                    self._note(out, line)
                    continue
                if not isinstance(out, tuple):
                    if not isinstance(out, StatusPacket):  # a record: the start is over
                        self._downloaded_at = None
                    return out
                self._skip(*out, line)
            if time.monotonic() >= deadline:
                return None
            self._fill()

    def starting_left(self, now: float) -> float:
        """Seconds left of the bridge's start (`BRIDGE_START_S` after its "FW downloaded" line) while no record has
        come since that line; 0 otherwise."""
        at = self._downloaded_at
        return 0.0 if at is None else max(0.0, at + BRIDGE_START_S - now)

    def _skip(self, kind: str, why: str, line: bytes) -> None:
        """Count a line that is not handed over. A separator is part of the protocol; every other one is a refused
        record, counted in bad_records too, which the device names when frames stop."""
        if kind == "separator":
            self._counts["separators"] += 1
            return
        self._counts[f"{kind}_lines"] += 1
        if kind == "partial_histogram" and self._counts[f"{kind}_lines"] == 1:
            log.warning("%s: %s", self.name, why)
        self._refuse(why, line)

    def _refuse(self, why: str, line: bytes) -> None:
        """Count a refused line; keep why, with how it began (the operator can tell noise from another sketch)."""
        self._counts["bad_records"] += 1
        self._counts["last_bad_record"] = f"{why} ('{_printable(line, LINE_EXCERPT_BYTES)}')"

    def _note(self, note: StatusPacket, line: bytes) -> None:
        """Count a download; keep the accuracy mode the bridge reports (`line`), and refuse to go on in another mode
        ams documents (long range, or an image without accuracy modes: not the `tmf8820` model's time axis), as the
        I2C backend refuses to start: a DeviceError, not a dropped link, so that the device's reader stops before any
        frame of that mode is made (a reopen would bring the frames back without the line on a board that does not
        reset). Any other value is no mode at all: a garbled line (a dropped or flipped character; the bridge has no
        checksum), refused and counted as a corrupt one, the mode left as it was; it must not stop the sensor."""
        if note.kind == "firmware_downloaded":
            self._counts["downloads"] = self._counts.get("downloads", 0) + 1
            self._downloaded_at = note.t
            return
        mode = int(note.text, 16)
        if mode not in RANGE_NAMES:
            self._counts["corrupt_lines"] += 1
            self._refuse(f"an Active range line with {note.text}, no accuracy mode ams documents (6E, 6F or 0)",
                         line)
            return
        self._counts["active_range"] = RANGE_NAMES[mode]
        if mode != RANGE_SHORT:
            raise DeviceError(bridge_mode_refusal(mode, note.text))

    def _fill(self) -> None:
        """Read what the port has (waiting at most 0.05 s) and split complete lines into _pending."""
        if self._ser is None:
            raise LinkDown("port is not open")
        try:
            # The port's own timeout stays at 0.05 s: setting it reconfigures the tty every time.
            chunk = self._ser.read(max(1, self._ser.in_waiting))
        except (serial.SerialException, OSError) as exc:
            raise LinkDown(f"read failed: {exc}") from None
        if not chunk:
            return
        t = time.monotonic()
        self._buf += chunk
        *lines, rest = self._buf.split(b"\n")
        self._pending.extend((bytes(line), t) for line in lines if line.strip())
        self._buf = bytearray(rest)
        if len(self._buf) > MAX_LINE_BYTES:
            self._counts["overlong_lines"] += 1
            self._refuse(f"a line of over {MAX_LINE_BYTES} bytes without a newline", bytes(self._buf))
            self._buf.clear()

    def close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):
                pass

    def counters(self) -> dict:
        return dict(self._counts)


class SerialSensor(TMF8820):
    """A TMF8820 on an Arduino bridge at `port` (1,000,000 baud; some sketches use 115,200).

    frame_timeout_s: a frame not complete this long after its first line is dropped. link_grace_s: how long the port
    may be gone (unplugged) before next_frame raises LinkLost; it is reopened with backoff meanwhile. address: the
    sensor's I2C address printed on each line (None accepts any). period_ms: the measurement period the bridge's
    firmware sets (a longer interval between frames, when observed, counts instead).
    """

    def __init__(self, port: str, baud: int = 1_000_000, *, model: SensorModel | None = None,
                 frame_timeout_s: float = 2.0, link_grace_s: float = 5.0, address: int | None = 0x41,
                 queue_frames: int = 256, period_ms: float = BRIDGE_PERIOD_MS):
        super().__init__(SerialBridgeTransport(port, baud, address, period_ms), model=model,
                         frame_timeout_s=frame_timeout_s, link_grace_s=link_grace_s, queue_frames=queue_frames)
