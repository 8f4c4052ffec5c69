"""The serial backend: the real pyserial on a pseudo-terminal fed by the simulated Arduino bridge.

Decoded histograms must equal what was sent, bit for bit; frames with corrupt, partial, missing, duplicated or
reordered lines must never come out, and the counters must say why."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import threading
import time

import numpy as np
import pytest

from spadscan.daemon.devices import LinkLost, SensorSilent
from spadscan.daemon.sensor.serial_bridge import SerialSensor, classify_line
from spadscan.daemon.sensor.sim_bridge import FAULTS, BridgeResult, SimBridge, frame_lines, obj_line, raw_lines
from spadscan.daemon.sensor.transport import HistogramPacket, ResultPacket, StatusPacket
from spadscan.protocol.errors import DeviceError


pytestmark = pytest.mark.usefixtures("no_leaked_threads_or_fds")


def counts(seed):
    return np.random.default_rng(seed).integers(0, 1 << 24, (10, 128))


def result(seed):
    rng = np.random.default_rng(seed)
    return BridgeResult(result_no=seed % 256, temperature_c=int(rng.integers(20, 61)), n_valid=9,
                        systick=int(rng.integers(0, 2**32)), distances_mm=rng.integers(0, 5000, 36).tolist(),
                        confidences=rng.integers(0, 256, 36).tolist())


# ---- line parsing ------------------------------------------------------------------------------------------------
def test_parse_raw_and_obj_lines():
    c = counts(1)
    lines = raw_lines(c)
    assert len(lines) == 30 and lines[13].startswith(b"#Raw,65,13,")
    pkt = classify_line(lines[13].rstrip(b"\n"), 1.5, 0x41)
    assert isinstance(pkt, HistogramPacket) and pkt.index == 13 and pkt.t == 1.5
    assert list(pkt.payload) == [(int(v) >> 8) & 0xFF for v in c[3]]  # channel 13 % 10, byte plane 13 // 10
    res = result(2)
    line = obj_line(res)
    assert len(line.rstrip(b",\r\n").split(b",")) == 78
    obj = classify_line(line.rstrip(b"\n"), 2.0, 0x41)
    assert isinstance(obj, ResultPacket)
    assert (obj.result_no, obj.temperature_c, obj.n_valid, obj.systick) == (2, res.temperature_c, 9, res.systick)
    assert obj.distances_mm == res.distances_mm and obj.confidences == res.confidences


@pytest.mark.parametrize("line, why", [
    (b"#Obj", "separator"),
    (b"#Raw,65,3,1,2,3", "corrupt"),  # truncated
    (b"#Raw,66,3," + b",".join([b"1"] * 128), "other_address"),
    (b"#Raw,65,30," + b",".join([b"1"] * 128), "corrupt"),  # sub-packet out of range
    (b"#Raw,65,3," + b",".join([b"1"] * 127) + b",-1", "corrupt"),
    (b"#Raw,65,3," + b",".join([b"1"] * 127) + b", 1", "corrupt"),
    (b"#Obj,65,1,25,9,100," + b",".join([b"1", b"300"] * 36), "corrupt"),  # confidence > 255
    (b"#Obj,65,1,nan,9,100," + b",".join([b"1", b"3"] * 36), "corrupt"),
    (b"#Obj,65,1,256,9,100," + b",".join([b"1", b"3"] * 36), "corrupt"),  # more than a byte
    (b"#Obj,65,1,-6,9,100," + b",".join([b"1", b"3"] * 36), "corrupt"),  # the firmware never prints a sign
    (b"#Obj,65,1,25,9,100," + b",".join([b"1", b"3"] * 35), "corrupt"),
    (b"12,13,14,15", "corrupt"),  # the tail of a line: a mid-line start
    (b"\xff\xfe#R", "corrupt"),
    (b"#Foo,1,2", "unknown"),
])
def test_malformed_lines_are_named(line, why):
    assert classify_line(line, 0.0, 0x41)[0] == why


def test_status_lines():
    err = classify_line(b"#Err,I2C,NACK\r", 0.0, 0x41)
    vers = classify_line(b"#Vers,1,2,3", 0.0, 0x41)
    assert isinstance(err, StatusPacket) and (err.kind, err.text) == ("error", "I2C,NACK")
    assert isinstance(vers, StatusPacket) and (vers.kind, vers.text) == ("version", "1,2,3")


def test_the_bridges_own_untagged_lines_are_status_not_noise():
    """The UW firmware prints "FW downloaded" after a download and "Active range: 6E" on every start, without a '#'."""
    downloaded = classify_line(b"FW downloaded\r", 0.0, 0x41)
    mode = classify_line(b"Active range: 6f", 0.0, 0x41)
    assert isinstance(downloaded, StatusPacket) and downloaded.kind == "firmware_downloaded"
    assert isinstance(mode, StatusPacket) and (mode.kind, mode.text) == ("active_range", "6F")
    assert classify_line(b"Active range: XYZ", 0.0, 0x41)[0] == "corrupt"


def test_a_bridge_start_is_counted_and_its_accuracy_mode_kept(arun, caplog):
    """In short range (6E) the bridge's start lines are counted and kept, and frames flow; any other mode is refused
    (test_sensor_reference_bridge)."""
    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge) as sensor:
                bridge.boot(0x6E)
                bridge.send_frame(counts(1), result(1))
                await sensor.next_frame(10)
                return sensor.counters()

    with caplog.at_level("WARNING", logger="spadscan.daemon"):
        c = arun(main())
    assert c["corrupt_lines"] == 0 and c["downloads"] == 1 and c["active_range"] == "short range"
    assert "short-range high accuracy" not in caplog.text


@pytest.mark.parametrize("fault", FAULTS)
def test_every_bridge_fault_spoils_the_frame(fault):
    good = frame_lines(counts(3), result(3))
    bad = frame_lines(counts(3), result(3), fault)
    assert bad != good


# ---- end to end over a pty ---------------------------------------------------------------------------------------
@contextlib.asynccontextmanager
async def streaming(bridge, **kw):
    """A SerialSensor streaming from the bridge's port; released and closed even when the test fails (no thread
    is left behind to hang the run)."""
    sensor = SerialSensor(bridge.port, **kw)
    try:
        await sensor.connect()
        await sensor.prepare()
        yield sensor
    finally:
        await sensor.release()
        await sensor.close()


@contextlib.asynccontextmanager
async def unplugged_after_a_frame():
    """(bridge, sensor): a sensor streaming from a bridge with a long link grace, its first frame delivered and its
    bridge then unplugged."""
    with SimBridge() as bridge:
        async with streaming(bridge, link_grace_s=30) as sensor:
            bridge.send_frame(counts(1))
            await sensor.next_frame(10)
            bridge.unplug()
            yield bridge, sensor


def test_frames_arrive_bit_for_bit_and_corrupt_frames_never_do(arun):
    sent_good = []

    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge) as sensor:
                bridge.send(b"1,2,3,4\n")  # we joined mid-line
                bridge.send(b"#Vers,1.0.4\r\n#Err,no target\r\n#Obj\n")
                bridge.send(b"".join(raw_lines(counts(99))[5:]))  # ... and mid-frame
                bridge.send(b"#Raw,66,0," + b",".join([b"7"] * 128) + b"\n")  # another sensor on the bridge
                for k, fault in enumerate((None,) + FAULTS + (None,)):
                    bridge.send_frame(counts(k), result(k), fault=fault)
                    if fault is None:
                        sent_good.append(k)
                    bridge.send_frame(counts(100 + k), result(100 + k))  # a good frame after every fault
                    sent_good.append(100 + k)
                got = [await sensor.next_frame(10) for _ in sent_good]
                counters = sensor.counters()
            return got, counters

    got, c = arun(main())
    for frame, k in zip(got, sent_good):
        assert np.array_equal(frame.hists, counts(k)[1:]) and np.array_equal(frame.reference, counts(k)[0])
        assert frame.hists.dtype == np.uint32
        assert frame.depths_mm == [float(d) for d in result(k).distances_mm]
        assert frame.confidences == result(k).confidences and frame.temperature_c == result(k).temperature_c
        assert frame.t_start <= frame.extra["t_first_packet"] <= frame.t_end
    assert all(a.t_end <= b.extra["t_first_packet"] for a, b in zip(got, got[1:]))
    assert c["frames"] == len(sent_good) and c["frames_delivered"] == len(sent_good)
    # Every faulty frame was dropped, except "no_result" and "bad_result", whose frames lose only their #Obj line
    # and are dropped when the next frame starts: all 9 are counted once.
    assert c["frames_dropped"] == len(FAULTS)
    assert c["dropped_no_result"] == 2 and c["dropped_out_of_order"] == len(FAULTS) - 2
    # mid-line start, truncate, garble, out_of_range, merge (two lines run into one), bad_result
    assert c["corrupt_lines"] == 6 and c["separators"] == 2 and c["other_address_lines"] == 1
    assert c["bad_records"] == 7  # every skipped line but the separators was refused
    assert c["firmware_version"] == "1.0.4" and c["last_status_error"] == "no target" and c["status_errors"] == 1


def test_unplug_and_replug(arun):
    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge, link_grace_s=0.3) as sensor:
                bridge.send_frame(counts(1))
                first = await sensor.next_frame(10)
                bridge.send(b"".join(raw_lines(counts(2))[:9]) + b"#Raw,65,9,1,2")  # unplugged mid-frame, mid-line
                bridge.flush()
                bridge.unplug()
                with pytest.raises(LinkLost, match="sensor serial .*link down .*grace 0.3 s"):
                    await sensor.next_frame(30)
                bridge.replug()
                while sensor.counters()["link"] == "down":
                    await asyncio.sleep(0.01)
                bridge.send_frame(counts(3))  # the bridge kept measuring: this one may predate the reopen
                bridge.send_frame(counts(5))
                after = await sensor.next_frame(10)
                counters = sensor.counters()
            return first, after, counters

    first, after, c = arun(main())
    assert np.array_equal(first.hists, counts(1)[1:]) and np.array_equal(after.hists, counts(5)[1:])
    assert c["link_drops"] == 1 and c["reconnects"] == 1 and c["reconnect_failures"] >= 1 and c["frames"] == 2
    assert first.t_end < after.extra["t_first_packet"] and after.t_start < after.extra["t_first_packet"]


def test_the_first_frame_after_a_reopen_is_dropped_as_its_exposure_may_predate_it(arun):
    """A bridge measures on its own: the frame whose first line arrives first after a reopen may have been exposed
    partly before it (e.g. while the arm still moved), so it has no honest t_start and is dropped; later frames
    count back from the previous one's result arrival."""

    async def main():
        async with unplugged_after_a_frame() as (bridge, sensor):
            bridge.replug()
            bridge.flush()
            while sensor.counters()["reconnects"] < 1:
                await asyncio.sleep(0.01)
            bridge.send_frame(counts(2))
            bridge.send_frame(counts(3))
            frame = await sensor.next_frame(10)
            counters = sensor.counters()
        return frame, counters

    frame, c = arun(main())
    assert np.array_equal(frame.hists, counts(3)[1:]) and c["dropped_link_reset"] == 1 and c["frames"] == 2
    assert frame.t_start <= frame.extra["t_first_packet"]  # counted back from the dropped frame's result arrival


def test_a_short_unplug_within_the_grace_loses_no_later_frame(arun):
    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge, link_grace_s=30) as sensor:
                bridge.unplug()
                bridge.replug()
                bridge.flush()
                while sensor.counters()["reconnects"] < 1:
                    await asyncio.sleep(0.01)
                for k in (4, 5, 6):  # the first may predate the reopen (dropped); none after it is lost
                    bridge.send_frame(counts(k))
                frames = [await sensor.next_frame(10) for _ in range(2)]
            return frames

    frames = arun(main())
    assert [np.array_equal(f.hists, counts(k)[1:]) for f, k in zip(frames, (5, 6))] == [True, True]


def test_a_bridge_that_reports_an_error_and_stops_is_named_in_the_silence(arun):
    """The UW firmware prints '#Err,inter,<status>,but no data' after a failed read and stops measuring for good:
    the SensorSilent message quotes that line until a frame arrives again."""

    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge) as sensor:
                bridge.send(b"#Err,no target\n")  # an error before a frame is superseded by the frame
                bridge.send_frame(counts(1))
                await sensor.next_frame(10)
                with pytest.raises(SensorSilent) as quiet:
                    await sensor.next_frame(0.05)
                bridge.send(b"#Err,inter,2,but no data\n")
                bridge.flush()
                while sensor.counters()["status_errors"] < 2:
                    await asyncio.sleep(0.01)
                with pytest.raises(SensorSilent) as stopped:
                    await sensor.next_frame(0.05)
                bridge.send_frame(counts(2))  # replugged: frames again, the error is history
                await sensor.next_frame(10)
                with pytest.raises(SensorSilent) as again:
                    await sensor.next_frame(0.05)
            return quiet.value, stopped.value, again.value

    quiet, stopped, again = arun(main())
    assert str(quiet).endswith("no complete frame within 0.05 s") and quiet.detail == ""
    assert re.search(r"no complete frame within 0.05 s; the bridge reported 'inter,2,but no data' \d+\.\d s ago and "
                     r"no frame since; the UW bridge firmware stops measuring .*: reset or replug the bridge$",
                     str(stopped))
    assert stopped.detail in str(stopped) and "\n" not in str(stopped)
    assert again.detail == ""


async def silence_after(bridge, sensor, lines: bytes, counter: str, least: int):
    """Send `lines`, wait until the sensor's `counter` reaches `least`, then the SensorSilent of a frame that does
    not come, and the counters then."""
    bridge.send(lines)
    bridge.flush()
    while sensor.counters()[counter] < least:
        await asyncio.sleep(0.01)
    with pytest.raises(SensorSilent) as refused:
        await sensor.next_frame(0.05)
    return refused.value, sensor.counters()


def test_a_bridge_whose_lines_are_all_refused_names_them_in_the_silence(arun):
    """A sensor on the bridge that receives only lines it refuses (partial lines, noise, another sensor's address)
    says so when frames stop: how many arrived since the last frame, and why the last one was refused."""

    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge) as sensor:
                bridge.send(b"12,13,14\n")  # refused before the frame: not the reason for a later silence
                bridge.send_frame(counts(1), result(1))
                await sensor.next_frame(10)
                lines = b"#Raw,65,3,1,2,3\n" + raw_lines(counts(2), address=0x42)[0] + b"#Obj\n\x93\xf1k\x02@\n"
                return await silence_after(bridge, sensor, lines, "bad_records", 4)

    refused, c = arun(main())
    last = ("a line without a '#' tag: part of a line, or noise (a baud rate other than the bridge's?) "
            "('\\x93\\xf1k\\x02@')")
    assert refused.detail == ("3 records arrived since the last frame but were refused (bad_records); "
                              f"the last one: {last}")
    assert str(refused).endswith(f"no complete frame within 0.05 s; {refused.detail}") and "\n" not in str(refused)
    assert (c["corrupt_lines"], c["other_address_lines"], c["separators"]) == (3, 1, 1)
    assert c["bad_records"] == 4 and c["last_bad_record"] == last


def test_a_line_too_long_is_a_refused_record(arun):
    """Bytes without a newline (a wrong baud rate, not a bridge) are dropped past 4096 and named in the silence."""

    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge) as sensor:
                # past the limit once, however the port splits it; no line ends
                return await silence_after(bridge, sensor, b"z" * 5000, "overlong_lines", 1)

    refused, c = arun(main())
    last = "the last one: a line of over 4096 bytes without a newline ('zzzzzzzzzzzzzzzzzzzzzzzz...')"
    assert refused.detail == f"1 record arrived since the last frame but was refused (bad_records); {last}"
    assert (c["overlong_lines"], c["bad_records"], c["corrupt_lines"]) == (1, 1, 0)


@pytest.mark.parametrize("line, why", [
    (b"#Obj", ("separator", "")),
    (b"#Raw,65,3,1,2,3", ("corrupt", "a #Raw line of 6 fields, not 131")),
    (b"#Raw,65,3," + b",".join([b"1"] * 127) + b",1x",
     ("corrupt", "a #Raw line with '1x', not a decimal number in 0..255")),
    (b"#Obj,65,1,25,9,100," + b",".join([b"1", b"300"] * 36),
     ("corrupt", "a #Obj line with a confidence of 300, more than a byte")),
    (b"#Obj,66,1,25,9,100," + b",".join([b"1", b"3"] * 36),
     ("other_address", "a #Obj line for I2C address 66, not 65")),
    (b"#Foo,1,2", ("unknown", "a #Foo line, a tag the bridge does not print")),
    # ams' shim prints electrical-calibration histograms under #Cal (the firmware set to dump them): named as such
    (b"#Cal,65,0,1,2", ("unknown", "a #Cal line: electrical-calibration histograms, which the bridge firmware prints "
                                   "only when set to dump them; it must dump raw histograms alone (HIST_DUMP = 1)")),
])
def test_a_skipped_line_says_why(line, why):
    """The reason a line is refused, as the silence quotes it (bad_records' last_bad_record)."""
    assert classify_line(line, 0.0, 0x41) == why


def test_a_missing_port_is_a_named_error_at_connect(arun, tmp_path):
    async def main():
        sensor = SerialSensor(str(tmp_path / "ttyNONE"))
        try:
            await sensor.connect()
        finally:
            await sensor.close()

    with pytest.raises(DeviceError, match=r"sensor serial .*ttyNONE: cannot open port at 1000000 baud"):
        arun(main())


def test_a_streaming_bridge_with_faults_delivers_only_whole_frames(arun):
    """The demo's use: a bridge that streams rendered frames and spoils every third one."""
    made = []

    def source():
        made.append(counts(len(made)))
        return made[-1]

    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge) as sensor:
                bridge.start_stream(source, period_s=0.01, fault_every=3)
                got = [await sensor.next_frame(10) for _ in range(8)]
                bridge.stop_stream()
                counters = sensor.counters()
            return got, counters

    got, c = arun(main())
    delivered = [next(k for k, m in enumerate(made) if np.array_equal(f.hists, m[1:])) for f in got]
    assert all(k % 3 != 2 for k in delivered)  # frames 3, 6, 9, ... (indices 2, 5, ...) carried a fault
    assert delivered == sorted(delivered) and c["frames_dropped"] >= 2


def test_close_is_prompt_and_drops_what_nobody_read():
    """Nobody reads the pty: close must not wait out the write timeout for each queued frame."""
    bridge = SimBridge(write_timeout_s=600.0)
    for k in range(20):  # ~16 KB each: more than a pty buffers
        bridge.send_frame(counts(k), result(k))
    released = []
    waiter = threading.Thread(target=lambda: released.append(_flushed(bridge)))
    waiter.start()
    deadline = time.monotonic() + 60
    while not any(kind == "mark" for kind, _ in list(bridge._queue.queue)):  # the flush waits behind the frames
        assert time.monotonic() < deadline, "flush never queued its mark"
        time.sleep(0.01)
    closer = threading.Thread(target=bridge.close)
    closer.start()
    closer.join(timeout=120)  # far below one write timeout, far above a loaded machine's scheduling
    waiter.join(timeout=120)
    assert not closer.is_alive(), "close waited for a reader"
    assert released == [True], "a flush waiter was left hanging"
    assert not os.path.lexists(bridge.port)
    assert bridge.counts["bytes_dropped"] > 0
    with pytest.raises(RuntimeError, match="flush after close"):
        bridge.flush()
    assert bridge.counts["bytes"] + bridge.counts["bytes_dropped"] == sum(
        len(b"".join(frame_lines(counts(k), result(k)))) for k in range(20))


def _flushed(bridge) -> bool:
    try:
        bridge.flush(timeout_s=120)
    except TimeoutError:
        return False
    return True


def test_a_silence_while_the_link_is_down_says_so_and_the_log_tells_the_drop_and_the_return(arun, caplog):
    async def main():
        async with unplugged_after_a_frame() as (bridge, sensor):
            while sensor.counters()["link"] == "up":
                await asyncio.sleep(0.01)
            with pytest.raises(SensorSilent) as silent:  # the frame timeout comes before the link's grace
                await sensor.next_frame(0.2)
            bridge.replug()
            while sensor.counters()["link"] == "down":
                await asyncio.sleep(0.01)
        return str(silent.value)

    with caplog.at_level(logging.INFO, logger="spadscan.daemon"):
        said = arun(main())
    assert "the link has been down for" in said and "it reconnects by itself" in said, said
    logged = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("sensor serial ") and ": link lost (" in m for m in logged), logged
    assert any(": link back after " in m for m in logged), logged
