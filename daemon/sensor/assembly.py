"""TMF8820 frame assembly: 30 histogram sub-packets and one result record make one frame.

Sub-packet n (0..29) holds byte plane n // 10 of channel n % 10 for 128 bins; a bin's count is
b0 + 256 b1 + 65536 b2 (24 bits). Channel 0 is the reference histogram (the laser pulse through an internal path),
channels 1..9 are the zones 0..8 of a capture.

A frame is accepted only when its sub-packets arrive complete and in order 0..29, followed by a result record.
Anything else (a missing, duplicated or out-of-order sub-packet, a result without a full histogram, a histogram
without a result, a frame that stalls) drops the frame whole and counts why, so a corrupt frame never reaches a
capture. These are plain functions and a state machine without threads or I/O.
"""

from __future__ import annotations

import collections
import math

import numpy as np

from spadscan.daemon.devices import Frame

from .transport import (N_CHANNELS, N_SUBPACKETS, SUBPACKET_BYTES, HistogramPacket, Packet, ResultPacket,
                        StatusPacket)

DROP_REASONS = ("out_of_order", "incomplete", "no_result", "stalled", "link_reset")
INTERVAL_WINDOW = 8
"""Complete frames whose intervals bound the sensor's actual period (the longest of them counts)."""


def decode_histograms(payloads: np.ndarray) -> np.ndarray:
    """Counts (10, 128) uint32 from the 30 sub-packet payloads (30, 128) uint8, in sub-packet order."""
    p = np.asarray(payloads)
    if p.shape != (N_SUBPACKETS, SUBPACKET_BYTES) or p.dtype != np.uint8:
        raise ValueError(f"sub-packet payloads must be (30, 128) uint8, got {p.shape} {p.dtype}")
    planes = p.reshape(3, N_CHANNELS, SUBPACKET_BYTES).astype(np.uint32)
    return planes[0] | (planes[1] << 8) | (planes[2] << 16)


def encode_histograms(counts: np.ndarray) -> np.ndarray:
    """The 30 sub-packet payloads (30, 128) uint8 that carry counts (10, 128) < 2**24; inverse of decode."""
    c = np.asarray(counts)
    if c.shape != (N_CHANNELS, SUBPACKET_BYTES) or not np.issubdtype(c.dtype, np.integer):
        raise ValueError(f"counts must be (10, 128) integers, got {c.shape} {c.dtype}")
    if c.min() < 0 or c.max() >= 1 << 24:
        raise ValueError(f"counts must lie in [0, 2**24), got [{c.min()}, {c.max()}]")
    c = c.astype(np.uint32)
    planes = np.stack([(c >> (8 * k)) & 0xFF for k in range(3)])  # (3, 10, 128)
    return planes.reshape(N_SUBPACKETS, SUBPACKET_BYTES).astype(np.uint8)


class FrameAssembler:
    """Turns a stream of packets into complete frames; counts every frame it drops and why.

    `frame_timeout_s`: a frame whose result has not arrived this long after its first sub-packet is dropped as
    'stalled' (its timestamps would lie).

    `t_start` of a frame is a lower bound on when its exposure began (`Frame`), from this timing model of the chip:
    it measures cyclically, one measurement after another, each within one period P; a finished measurement waits in
    a one-frame buffer, a newer one replacing it, until the previous frame has been handed over (the host cleared
    its last record). So the frame handed over next finished measuring no earlier than one period before that
    hand-over, and began no earlier than two periods before it. The hand-over came after the arrival of the last
    record before the frame's first sub-packet (normally the previous frame's result), less `lag_s` (a bridge
    prints a record after it read it): t_start = that arrival - 2 P - lag_s. P is the longest of the configured
    `period_s` and the intervals between the last INTERVAL_WINDOW complete frames (a measurement that takes longer
    than the configured period stretches it). After `restart(t)` or `reset(t)` with restarted=True (the sensor was
    told to start measuring at t) no exposure began before t, and t_start is never earlier than that. The arrival
    of its first sub-packet is kept in `extra['t_first_packet']`. After `reset` with restarted=False (the sensor
    kept measuring on its own: a bridge after a reopen) the first frame has no earlier arrival to count back from
    and is dropped ('link_reset').

    `silent_cause` is the last error the link reported (a bridge's `#Err` line) since the last complete frame, with
    its arrival time, or None: why frames may have stopped.
    """

    def __init__(self, frame_timeout_s: float = 2.0, t0: float = 0.0, period_s: float = 0.0, lag_s: float = 0.0):
        if not frame_timeout_s > 0:
            raise ValueError(f"frame timeout {frame_timeout_s} s must be positive")
        if not (period_s >= 0 and lag_s >= 0):
            raise ValueError(f"period {period_s} s and arrival lag {lag_s} s must be >= 0")
        self.frame_timeout_s = frame_timeout_s
        self.period_s, self.lag_s = period_s, lag_s
        self.counts = {"frames": 0, "packets": 0, "packets_discarded": 0, "status_errors": 0}
        self.dropped = {reason: 0 for reason in DROP_REASONS}
        self.last_status_error = ""
        self.silent_cause: tuple[str, float] | None = None
        self.firmware_version = ""
        self._payloads = np.zeros((N_SUBPACKETS, SUBPACKET_BYTES), np.uint8)
        self._expected: int | None = None  # next sub-packet index of the frame in progress; None: none in progress
        self._t_first = 0.0
        self._t_start = 0.0
        self._t_last = t0
        self._unbounded_next = False  # the next frame to start may have been exposed before a reset
        self._unbounded = False  # the frame in progress is that frame
        self._floor = -math.inf  # when the sensor was last told to start measuring: no exposure began before it
        self._t_prev_end: float | None = None  # the last complete frame's result arrival (or the restart), or None
        self._intervals: collections.deque[float] = collections.deque(maxlen=INTERVAL_WINDOW)

    def reset(self, t: float, restarted: bool = True, drop_first: bool | None = None) -> None:
        """Forget a frame in progress (the link was reset at monotonic time t). restarted: the sensor was told to
        start measuring at t, so later frames start after t; False: it kept measuring, and the first frame that
        starts after t is dropped (its exposure may have begun before t) unless drop_first=False says that t bounds
        it as a record's arrival would (the link was emptied at t and reads live from then on)."""
        if self._expected is not None:
            self._drop("link_reset")
        self._mark(t, restarted, (not restarted) if drop_first is None else drop_first)

    def restart(self, t: float) -> bool:
        """The sensor was told at t to stop and start a fresh measurement: forget the frame in progress (returns
        whether there was one; it is discarded on purpose, not counted as dropped); later frames start after t."""
        discarded = self._expected is not None
        self._expected = None
        self._mark(t, True, False)
        return discarded

    def lookback_s(self) -> float:
        """How long before the last record's arrival the next frame's exposure may have begun, s."""
        return 2 * max([self.period_s, *self._intervals]) + self.lag_s

    def _mark(self, t: float, restarted: bool, drop_first: bool) -> None:
        self._t_last = t
        if restarted:
            self._floor = t
        self._t_prev_end = t if restarted else None  # a restart starts the first measurement's interval
        self._unbounded_next = drop_first

    def feed(self, pkt: Packet) -> Frame | None:
        """Take one packet; returns a frame when this packet completed one."""
        self.counts["packets"] += 1
        if isinstance(pkt, StatusPacket):
            if pkt.kind == "error":
                self.counts["status_errors"] += 1
                self.last_status_error = pkt.text
                self.silent_cause = (pkt.text, pkt.t)
            elif pkt.kind == "version":
                self.firmware_version = pkt.text
            return None
        if self._expected is not None and pkt.t - self._t_first > self.frame_timeout_s:
            self._drop("stalled")
        frame = None
        if isinstance(pkt, HistogramPacket):
            self._take_subpacket(pkt)
        elif isinstance(pkt, ResultPacket):
            frame = self._take_result(pkt)
        self._t_last = pkt.t
        return frame

    def counters(self) -> dict:
        out = dict(self.counts)
        out["frames_dropped"] = sum(self.dropped.values())
        out.update({f"dropped_{k}": v for k, v in self.dropped.items()})
        if self.last_status_error:
            out["last_status_error"] = self.last_status_error
        if self.firmware_version:
            out["firmware_version"] = self.firmware_version
        return out

    # ---- the state machine ---------------------------------------------------------------------------------------
    def _drop(self, reason: str) -> None:
        self.dropped[reason] += 1
        self._expected = None

    def _take_subpacket(self, pkt: HistogramPacket) -> None:
        if len(pkt.payload) != SUBPACKET_BYTES or not 0 <= pkt.index < N_SUBPACKETS:
            raise ValueError(f"sub-packet {pkt.index} with {len(pkt.payload)} bytes is malformed")
        if pkt.index == 0:
            if self._expected is not None:
                self._drop("no_result" if self._expected == N_SUBPACKETS else "incomplete")
            self._expected = 0
            self._t_first = pkt.t
            self._t_start = max(self._floor, self._t_last - self.lookback_s())
            self._unbounded, self._unbounded_next = self._unbounded_next, False
        elif self._expected != pkt.index:
            # Missing, duplicated or out of order (or we joined mid-frame): wait for the next sub-packet 0.
            if self._expected is not None:
                self._drop("out_of_order")
            self.counts["packets_discarded"] += 1
            return
        self._payloads[pkt.index] = np.frombuffer(pkt.payload, np.uint8)
        self._expected = pkt.index + 1

    def _take_result(self, pkt: ResultPacket) -> Frame | None:
        if self._expected != N_SUBPACKETS:
            if self._expected is None:
                self.counts["packets_discarded"] += 1  # e.g. the tail of a frame we joined mid-way
            else:
                self._drop("incomplete")
            return None
        self._expected = None
        if self._t_prev_end is not None:
            self._intervals.append(pkt.t - self._t_prev_end)
        self._t_prev_end = pkt.t
        if self._unbounded:
            self._unbounded = False
            self.dropped["link_reset"] += 1
            return None
        self.silent_cause = None
        counts = decode_histograms(self._payloads)
        self.counts["frames"] += 1
        return Frame(
            hists=counts[1:].copy(),
            reference=counts[0].copy(),
            t_start=self._t_start,
            t_end=pkt.t,
            temperature_c=float(pkt.temperature_c),
            depths_mm=[float(d) for d in pkt.distances_mm],
            confidences=[int(c) for c in pkt.confidences],
            extra={"t_first_packet": self._t_first, "result_no": pkt.result_no, "n_valid": pkt.n_valid,
                   "systick": pkt.systick, **pkt.extra},
        )
