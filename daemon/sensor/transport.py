"""The small byte-level interface between the TMF8820 device logic and the link that carries its data.

A transport delivers the sensor's records one at a time: histogram sub-packets (128 raw bytes each, 30 per frame)
and result records (on-chip distances). The serial bridge, the I2C bus and their simulated twins implement it; the
`TMF8820` class assembles frames from what they deliver and owns the threading, timeouts and reconnection.

Every method blocks and is called from the device's one dedicated thread only, never from the event loop.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

from spadscan.protocol.errors import DeviceError

N_SUBPACKETS = 30
"""Histogram sub-packets per frame: 10 channels x 3 byte planes."""
SUBPACKET_BYTES = 128
"""Payload bytes per sub-packet: one byte plane of 128 bins."""
N_CHANNELS = 10
"""Channel 0 is the reference histogram, channels 1..9 the 3x3 zones."""
N_RESULTS = 36
"""Result slots (distance, confidence) in one result record."""


# ACTIVE_RANGE (register 0x19) as ams' application reports it; the UW bridge prints it as "Active range: <hex>".
RANGE_NONE, RANGE_SHORT, RANGE_LONG = 0x00, 0x6E, 0x6F
RANGE_NAMES = {RANGE_NONE: "no accuracy modes", RANGE_SHORT: "short range", RANGE_LONG: "long range"}


class LinkDown(DeviceError):
    """The link failed under a transport (port vanished, bus error). The device reopens it with backoff."""


@dataclass
class HistogramPacket:
    """One histogram sub-packet: `index` 0..29 (channel index % 10, byte plane index // 10), 128 payload bytes.

    `t` is the monotonic time (s) the packet arrived.
    """

    index: int
    payload: bytes
    t: float


@dataclass
class ResultPacket:
    """One result record: the sensor's own distance estimates that close a frame.

    distances_mm / confidences: 36 entries each, in the record's slot order (slot k: target k // 18 + 1 of channel
    k % 9 + 1, `i2c_records.slot_target`; not zone k); temperature_c: the record's unsigned temperature byte, deg C;
    n_valid: the slots holding a target; `t` is the monotonic arrival time (s).
    """

    result_no: int
    temperature_c: float
    n_valid: int
    systick: int
    distances_mm: list[int]
    confidences: list[int]
    t: float
    extra: dict = field(default_factory=dict)


@dataclass
class StatusPacket:
    """A message from the link that is not data: kind 'error' (`#Err`) or 'version' (`#Vers`), with its text."""

    kind: str
    text: str
    t: float


Packet = HistogramPacket | ResultPacket | StatusPacket


class Transport(abc.ABC):
    """A link to one TMF8820. Implementations count what they skip in `counters()`: each its own detailed counters,
    and all of them the records they read and refused (malformed, or not this sensor's) as `bad_records`, with the
    reason for the last one in `last_bad_record`, so that a device whose frames stop can say why in the same words
    whatever the link.

    Lifecycle: open -> start -> read_packet ... -> stop -> close. After a `LinkDown` the device calls close, then
    open and start again (with backoff) until the link is back.
    """

    name: str = "transport"
    """Human-readable name of the link (port, bus and address), used in error messages."""
    restarts_measurement: bool = True
    """`start` tells the sensor to start measuring, so nothing read after it was exposed before it. False: the sensor
    measures on its own (a bridge), and the first frame after a reopen may have been exposed before it."""
    error_hint: str = ""
    """What to do when frames stop after the link reported an error (its `#Err` line), for the SensorSilent message."""
    period_s: float = 0.0
    """The measurement period the sensor is configured with, s: the shortest time from one measurement's start to
    the next (a measurement that takes longer stretches it; the device also uses the interval it observes)."""
    arrival_lag_s: float = 0.0
    """How much later than the sensor's hand-over of a record its arrival time can be, s: 0 when the host reads the
    chip itself; a bridge reads, then prints, then the USB link delivers."""

    @abc.abstractmethod
    def open(self) -> None:
        """Open the link. Raises LinkDown when the port or bus is not there (yet)."""

    def start(self) -> None:
        """Bring the sensor to streaming frames (boot, configure, start measuring). Default: nothing to do."""

    @abc.abstractmethod
    def read_packet(self, timeout_s: float) -> Packet | None:
        """The next well-formed record, or None when none arrived within timeout_s. Raises LinkDown."""

    def starting_left(self, now: float) -> float:
        """Seconds (time.monotonic() `now`) the sensor may still take to deliver its first record after a start the
        link has seen it begin on its own (a bridge that reset and set the sensor up again: `serial_bridge.py`), 0
        when none is under way. Default: 0 (a start the host drives itself is awaited in `start`)."""
        return 0.0

    def restart(self) -> None:
        """Stop the measurement and start a fresh one, so that nothing read after it was exposed before it; records
        of the old measurement are not handed over any more. Only for `restarts_measurement` transports. Default:
        `stop`, then `start`."""
        self.stop()
        self.start()

    def stop(self) -> None:
        """Stop measuring (best effort). Default: nothing to do."""

    @abc.abstractmethod
    def close(self) -> None:
        """Close the link; idempotent, never raises."""

    def counters(self) -> dict:
        """What the link skipped or saw: name -> int or str. `bad_records` (int: records read and refused) and, once
        one was, `last_bad_record` (str: why the last one was, in words for the operator) mean the same for every
        transport; the rest are its own (corrupt lines, boots, ...)."""
        return {}
