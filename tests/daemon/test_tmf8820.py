"""TMF8820 device logic: sub-packet decoding, frame assembly and its drop rules, and the device over a scripted
transport (threading, timeouts, link loss and reconnection)."""

from __future__ import annotations

import asyncio
import os
import threading
import time

import numpy as np
import pytest

from spadscan.daemon.devices import LinkLost, SensorSilent
from spadscan.daemon.sensor.assembly import FrameAssembler, decode_histograms, encode_histograms
from spadscan.daemon.sensor.tmf8820 import TMF8820
from spadscan.daemon.sensor.transport import HistogramPacket, LinkDown, ResultPacket, StatusPacket, Transport
from spadscan.protocol.errors import DeviceError
from spadscan.protocol.sensor_presets import sensor_preset


pytestmark = pytest.mark.usefixtures("no_leaked_threads_or_fds")


def packets_for(counts, t0=0.0, result_no=0, dt=0.001):
    """The 31 packets of one frame (spec: sub-packet n = byte plane n // 10 of channel n % 10), written out
    independently of encode_histograms."""
    pkts = []
    for n in range(30):
        plane = [(int(v) >> (8 * (n // 10))) & 0xFF for v in counts[n % 10]]
        pkts.append(HistogramPacket(n, bytes(plane), t0 + n * dt))
    pkts.append(ResultPacket(result_no, 31.0, 9, 1234, list(range(36)), [200] * 36, t0 + 30 * dt))
    return pkts


def random_counts(seed):
    return np.random.default_rng(seed).integers(0, 1 << 24, (10, 128))


def feed_all(asm, pkts):
    return [f for f in (asm.feed(p) for p in pkts) if f is not None]


def test_decode_follows_the_wire_layout():
    payloads = np.zeros((30, 128), np.uint8)
    payloads[13, 5] = 7  # sub-packet 13: channel 3, byte plane 1
    payloads[29, 127] = 2  # sub-packet 29: channel 9, byte plane 2
    payloads[0, 0] = 255  # sub-packet 0: channel 0 (reference), plane 0
    counts = decode_histograms(payloads)
    assert counts.dtype == np.uint32 and counts.shape == (10, 128)
    assert counts[3, 5] == 7 * 256 and counts[9, 127] == 2 * 65536 and counts[0, 0] == 255
    assert counts.sum() == 7 * 256 + 2 * 65536 + 255


def test_encode_inverts_decode_and_rejects_overflow():
    counts = random_counts(1)
    counts[0, 0], counts[1, 1] = 0, (1 << 24) - 1
    assert np.array_equal(decode_histograms(encode_histograms(counts)), counts)
    with pytest.raises(ValueError):
        encode_histograms(np.full((10, 128), 1 << 24))


def test_a_frame_is_assembled_bit_for_bit_with_reference_and_result():
    asm = FrameAssembler(t0=0.5)
    counts = random_counts(2)
    (frame,) = feed_all(asm, packets_for(counts, t0=1.0))
    assert np.array_equal(frame.hists, counts[1:]) and np.array_equal(frame.reference, counts[0])
    assert frame.hists.dtype == np.uint32 and frame.hists.shape == (9, 128)
    assert frame.t_start == 0.5 and frame.t_end == pytest.approx(1.03) and frame.extra["t_first_packet"] == 1.0
    assert frame.temperature_c == 31.0 and frame.depths_mm[:3] == [0.0, 1.0, 2.0] and frame.confidences[0] == 200
    assert asm.counters()["frames"] == 1 and asm.counters()["frames_dropped"] == 0


def test_next_frame_counts_back_two_periods_and_the_lag_from_the_previous_result():
    """The chip hands a frame over after the previous one's last record was cleared; it finished measuring no more
    than a period before that, and began a period earlier still: t_start is a lower bound on its exposure."""
    asm = FrameAssembler(period_s=0.1, lag_s=0.02)
    frames = feed_all(asm, packets_for(random_counts(3), t0=1.0) + packets_for(random_counts(4), t0=2.0))
    assert frames[1].t_start == pytest.approx(frames[0].t_end - 2 * 0.1 - 0.02)


def test_a_period_longer_than_configured_counts_once_observed():
    """A measurement that takes longer than the configured period stretches it: the longest interval between the
    last complete frames counts instead."""
    asm = FrameAssembler(period_s=0.1)
    asm.reset(0.0)  # told to start measuring at 0: the first interval runs from there
    frames = feed_all(asm, [p for k in range(4) for p in packets_for(random_counts(30 + k), t0=0.5 + 0.5 * k)])
    assert frames[0].t_start == 0.0  # the restart bounds the first frame
    assert asm.lookback_s() == pytest.approx(2 * 0.53)  # 0 -> 0.53, then 0.5 s between results
    assert frames[3].t_start == pytest.approx(frames[2].t_end - 2 * 0.53)


def test_a_restart_discards_the_frame_in_progress_and_bounds_later_frames_by_it():
    asm = FrameAssembler(period_s=0.1)
    feed_all(asm, packets_for(random_counts(40), t0=1.0)[:12])
    assert asm.restart(2.0) is True and asm.restart(2.0) is False
    frames = feed_all(asm, packets_for(random_counts(41), t0=2.2) + packets_for(random_counts(42), t0=2.3))
    assert [f.t_start for f in frames] == [2.0, 2.0]  # never before the restart, though 2.23 - 2 x 0.23 is
    assert np.array_equal(frames[0].hists, random_counts(41)[1:]) and asm.counters()["frames_dropped"] == 0


@pytest.mark.parametrize("fault, reason", [
    ("drop", "out_of_order"), ("duplicate", "out_of_order"), ("swap", "out_of_order"),
    ("no_result", "no_result"), ("cut", "incomplete"),
])
def test_faulty_frames_are_dropped_whole_and_counted(fault, reason):
    asm = FrameAssembler()
    bad, good = packets_for(random_counts(5), t0=1.0), packets_for(random_counts(6), t0=2.0)
    if fault == "drop":
        del bad[12]
    elif fault == "duplicate":
        bad.insert(12, bad[12])
    elif fault == "swap":
        bad[12], bad[13] = bad[13], bad[12]
    elif fault == "no_result":
        bad.pop()
    elif fault == "cut":
        bad = bad[:10] + bad[-1:]  # a result after only 10 sub-packets
    frames = feed_all(asm, bad + good)
    assert len(frames) == 1 and np.array_equal(frames[0].hists, random_counts(6)[1:])
    assert asm.dropped[reason] == 1 and asm.counters()["frames_dropped"] == 1


def test_joining_mid_frame_waits_for_sub_packet_zero():
    asm = FrameAssembler()
    frames = feed_all(asm, packets_for(random_counts(7), t0=1.0)[17:] + packets_for(random_counts(8), t0=2.0))
    assert len(frames) == 1 and np.array_equal(frames[0].reference, random_counts(8)[0])
    assert asm.counts["packets_discarded"] == 14 and asm.counters()["frames_dropped"] == 0


def test_stalled_frames_and_link_resets_drop_the_frame_in_progress():
    asm = FrameAssembler(frame_timeout_s=0.5)
    pkts = packets_for(random_counts(9), t0=1.0)
    for p in pkts[20:]:
        p.t += 1.0  # the second part arrives a second later
    assert feed_all(asm, pkts) == [] and asm.dropped["stalled"] == 1
    feed_all(asm, packets_for(random_counts(9), t0=5.0)[:5])
    asm.reset(6.0)
    assert asm.dropped["link_reset"] == 1
    (frame,) = feed_all(asm, packets_for(random_counts(10), t0=7.0))
    assert frame.t_start == 6.0  # 6.0 - 2 x the longest interval seen, but no later frame began before the restart


def test_after_a_reset_without_a_restart_the_first_frame_is_dropped():
    """A sensor told to start measuring at the reset exposes nothing before it: its first frame starts there. One that
    kept measuring (a bridge after a reopen) may have exposed that frame partly before: it has no start to give."""
    asm = FrameAssembler(period_s=0.25)
    asm.reset(6.0, restarted=False, drop_first=False)  # a bridge's link emptied at 6.0: counted back from there
    (frame,) = feed_all(asm, packets_for(random_counts(10), t0=7.0))
    assert frame.t_start == 5.5 and asm.dropped["link_reset"] == 0
    asm.reset(8.0, restarted=False)
    frames = feed_all(asm, packets_for(random_counts(11), t0=9.0) + packets_for(random_counts(12), t0=10.0))
    assert len(frames) == 1 and np.array_equal(frames[0].hists, random_counts(12)[1:])
    assert frames[0].t_start == pytest.approx(9.03 - 0.5) and asm.dropped["link_reset"] == 1
    assert asm.counters()["frames"] == 2  # a dropped frame is not a frame


def test_status_packets_are_counted_not_framed():
    asm = FrameAssembler()
    feed_all(asm, [StatusPacket("error", "I2C NACK", 1.0), StatusPacket("version", "1.2.3", 1.1)])
    c = asm.counters()
    assert c["status_errors"] == 1 and c["last_status_error"] == "I2C NACK" and c["firmware_version"] == "1.2.3"


# ---- the device over a scripted transport ------------------------------------------------------------------------
class ScriptedTransport(Transport):
    """Replays queued packets; 'down' entries raise LinkDown; `opens_fail` refuses that many reopen attempts."""

    name = "scripted"

    def __init__(self):
        self.script: list = []
        self.lock = threading.Lock()
        self.opens = self.starts = self.stops = self.closes = 0
        self.opens_fail = 0

    def push(self, *items):
        with self.lock:
            self.script.extend(items)

    def open(self):
        if self.opens_fail:
            self.opens_fail -= 1
            raise LinkDown("port gone")
        self.opens += 1

    def start(self):
        self.starts += 1

    def read_packet(self, timeout_s):
        with self.lock:
            item = self.script.pop(0) if self.script else None
        if item is None:
            time.sleep(min(timeout_s, 0.01))
            return None
        if item == "down":
            raise LinkDown("cable pulled")
        item.t = time.monotonic()
        return item

    def stop(self):
        self.stops += 1

    def close(self):
        self.closes += 1


def test_device_streams_frames_and_stops_cleanly(arun):
    tr = ScriptedTransport()
    dev = TMF8820(tr)

    async def main():
        with pytest.raises(DeviceError, match="before prepare"):
            await dev.next_frame(0.1)
        await dev.connect()
        await dev.prepare()
        tr.push(*packets_for(random_counts(11)), *packets_for(random_counts(12)))
        f1, f2 = await dev.next_frame(5), await dev.next_frame(5)
        with pytest.raises(SensorSilent, match="sensor scripted: no complete frame within 0.2 s"):
            await dev.next_frame(0.2)
        await dev.release()
        await dev.close()
        return f1, f2

    f1, f2 = arun(main())
    assert np.array_equal(f1.hists, random_counts(11)[1:]) and np.array_equal(f2.hists, random_counts(12)[1:])
    assert f1.t_start <= f1.extra["t_first_packet"] <= f1.t_end <= f2.extra["t_first_packet"]
    assert f2.t_start == f1.t_start  # two observed intervals back is before the start of measuring at prepare
    assert (tr.opens, tr.starts, tr.stops, tr.closes) == (1, 1, 1, 1)
    c = dev.counters()
    assert c["frames_delivered"] == 2 and c["silent_timeouts"] == 1 and c["link"] == "up"


class RefusingTransport(ScriptedTransport):
    """A scripted transport whose 'refused' entries are records it read and refused, counted as the I2C one does."""

    def __init__(self):
        super().__init__()
        self.refused = 0

    def read_packet(self, timeout_s):
        with self.lock:
            refused = bool(self.script) and self.script[0] == "refused"
            if refused:
                self.script.pop(0)
                self.refused += 1
        return None if refused else super().read_packet(timeout_s)

    def counters(self):
        return {"bad_records": self.refused, "last_bad_record": "result: RID 0x11, not 0x10 (measurement result)"}


def test_silence_names_the_records_refused_since_the_last_frame(arun):
    tr = RefusingTransport()
    dev = TMF8820(tr)

    async def until_read(n_refused):
        while tr.refused < n_refused or tr.script:
            await asyncio.sleep(0.01)

    async def main():
        await dev.connect()
        await dev.prepare()
        errors = []
        try:
            tr.push("refused", "refused", *packets_for(random_counts(15)))
            await dev.next_frame(5)  # the refusals before this frame are not the reason for a later silence
            with pytest.raises(SensorSilent) as info:
                await dev.next_frame(0.1)
            errors.append(info.value)
            for n_refused in (3, 5):  # in all: 2 before the frame, then 1 and 2 more
                tr.push(*["refused"] * (n_refused - tr.refused))
                await until_read(n_refused)
                with pytest.raises(SensorSilent) as info:
                    await dev.next_frame(0.1)
                errors.append(info.value)
        finally:
            await dev.release()
            await dev.close()
        return errors

    quiet, one, three = arun(main())
    assert str(quiet) == "sensor scripted: no complete frame within 0.1 s" and quiet.detail == ""
    last = "the last one: result: RID 0x11, not 0x10 (measurement result)"
    assert one.detail == f"1 record arrived since the last frame but was refused (bad_records); {last}"
    assert three.detail == f"3 records arrived since the last frame but were refused (bad_records); {last}"
    assert str(three) == f"sensor scripted: no complete frame within 0.1 s; {three.detail}"


def test_device_reconnects_and_raises_link_lost_only_after_the_grace(arun):
    tr = ScriptedTransport()
    dev = TMF8820(tr, link_grace_s=0.3, backoff_s=(0.01, 0.05))

    async def main():
        await dev.connect()
        await dev.prepare()
        tr.opens_fail = 10**6  # unplugged and stays away
        tr.push(*packets_for(random_counts(13))[:12], "down")
        t0 = time.monotonic()
        with pytest.raises(LinkLost, match="link down for .*cable pulled|port gone"):
            await dev.next_frame(30)
        waited = time.monotonic() - t0
        assert dev.counters()["link"] == "down" and dev.counters()["reconnect_failures"] > 0
        tr.opens_fail = 0  # replugged
        while dev.counters()["link"] == "down":
            await asyncio.sleep(0.01)
        tr.push(*packets_for(random_counts(14)))
        frame = await dev.next_frame(5)
        await dev.release()
        await dev.close()
        return frame, waited

    frame, waited = arun(main())
    assert 0.25 < waited < 10
    assert np.array_equal(frame.hists, random_counts(14)[1:])
    c = dev.counters()
    assert c["link_drops"] == 1 and c["reconnects"] == 1 and c["dropped_link_reset"] == 1 and tr.starts == 2


def test_device_keeps_the_newest_frames_when_nobody_reads(arun):
    tr = ScriptedTransport()
    dev = TMF8820(tr, queue_frames=2)

    async def main():
        await dev.connect()
        await dev.prepare()
        for k in range(4):
            tr.push(*packets_for(random_counts(20 + k)))
        while dev.counters()["frames"] < 4:
            await asyncio.sleep(0.01)
        frames = [await dev.next_frame(1), await dev.next_frame(1)]
        await dev.close()
        return frames

    frames = arun(main())
    assert [np.array_equal(f.reference, random_counts(22 + k)[0]) for k, f in enumerate(frames)] == [True, True]
    assert dev.counters()["frames_overflowed"] == 2


def test_device_refuses_a_model_that_is_not_a_tmf8820():
    with pytest.raises(DeviceError, match="9 zones x 128 bins.*'lcspc-sim' has 1 zones x 1024 bins"):
        TMF8820(ScriptedTransport(), model=sensor_preset("lcspc-sim"))
