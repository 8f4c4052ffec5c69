"""The serial bridge and its twin against what the reference firmware prints and its consumer reads: `#Obj` and
`#Raw` lines without a trailing comma (exactly 78 and 131 fields), the temperature as an unsigned byte, the 6-bit
valid count (a printed count over 36 refused unless bits 7:6 explain it), `#Prt` (partial histogram) lines refused
with one line that says what to set, and a bridge that reports any mode but short range refused before a frame."""

from __future__ import annotations

import asyncio
import logging
import time

import numpy as np
import pytest

from spadscan.daemon.devices import SensorSilent
from spadscan.protocol.errors import DeviceError
from spadscan.daemon.sensor.serial_bridge import BRIDGE_START_S, classify_line
from spadscan.daemon.sensor.sim_bridge import BridgeResult, SimBridge, obj_line, raw_lines
from spadscan.daemon.sensor.transport import ResultPacket

from test_sensor_serial import counts, result, streaming

pytestmark = pytest.mark.usefixtures("no_leaked_threads_or_fds")

OBJ_PAIRS = b",".join([b"1", b"3"] * 36)


def consumer_fields(line: bytes) -> list[str]:
    """A line's fields as the UW consumer splits them: \\r and \\n removed, split on every comma."""
    return line.decode().replace("\r", "").replace("\n", "").split(",")


# ---- 6. the lines the firmware prints ------------------------------------------------------------------------------
def test_the_twin_prints_obj_and_raw_lines_as_the_firmware_does():
    """ams' print_results ends an #Obj line after the last confidence (no comma) with the firmware's '\\n'; the UW
    consumer takes an #Obj line of exactly 78 fields and a #Raw line of exactly 131."""
    line = obj_line(result(4))
    assert line.endswith(b"\n") and not line.endswith(b",\n")
    assert b"\r" not in line and len(consumer_fields(line)) == 78
    assert all(len(consumer_fields(raw)) == 131 and not raw.endswith(b",\n") for raw in raw_lines(counts(4)))
    assert consumer_fields(line)[-1] == str(result(4).confidences[-1])


@pytest.mark.parametrize("ending", [b"", b",", b"\r", b",\r"])
def test_the_parser_still_takes_a_trailing_comma_and_a_carriage_return(ending):
    obj = classify_line(b"#Obj,65,1,25,9,100," + OBJ_PAIRS + ending, 0.0, 0x41)
    assert isinstance(obj, ResultPacket) and obj.n_valid == 9 and obj.confidences == [3] * 36


def test_the_twin_counts_valid_results_as_the_chip_does():
    res = BridgeResult(distances_mm=[500] * 9 + [0] * 27, confidences=[40] * 5 + [0] * 31)
    assert consumer_fields(obj_line(res))[4] == "5"
    assert consumer_fields(obj_line(BridgeResult(n_valid=7)))[4] == "7"  # an explicit count is printed as given


# ---- 2. the temperature ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("printed", [b"0", b"25", b"127", b"128", b"200", b"255"])
def test_the_printed_temperature_is_an_unsigned_byte(printed):
    obj = classify_line(b"#Obj,65,1," + printed + b",9,100," + OBJ_PAIRS, 0.0, 0x41)
    assert isinstance(obj, ResultPacket) and obj.temperature_c == float(printed)


def test_the_twin_prints_what_a_chip_reports():
    assert consumer_fields(obj_line(BridgeResult(temperature_c=45)))[3] == "45"
    assert consumer_fields(obj_line(BridgeResult()))[3] == "25"  # the default: a bench's die temperature
    for bad in (-6, 256):
        with pytest.raises(ValueError, match="unsigned byte, 0..255"):
            obj_line(BridgeResult(temperature_c=bad))


def test_a_frame_keeps_the_temperature_the_bridge_printed(arun):
    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge) as sensor:
                bridge.send_frame(counts(7), BridgeResult(temperature_c=200, systick=3))
                return await sensor.next_frame(10)

    frame = arun(main())
    assert frame.temperature_c == 200.0 and np.array_equal(frame.hists, counts(7)[1:])


# ---- 3. the valid count ----------------------------------------------------------------------------------------------
def chip_obj_line(printed_count: int, n_first: int = 6, n_second: int = 3) -> bytes:
    """An #Obj line as ams' print_results prints a result of SPAD map 1: slots 0-8 the zones' first targets (the first
    `n_first` of them found), 18-26 second targets behind them (`n_second`), every other pair 0,0; the count byte
    printed whole as `printed_count`."""
    distances, confidences = [0] * 36, [0] * 36
    for zone in range(n_first):
        distances[zone], confidences[zone] = 400 + 10 * zone, 120
    for zone in range(n_second):
        distances[18 + zone], confidences[18 + zone] = 900 + 10 * zone, 40
    pairs = ",".join(f"{d},{c}" for d, c in zip(distances, confidences))
    return f"#Obj,65,7,31,{printed_count},123456,{pairs}".encode()


@pytest.mark.parametrize("printed, n_valid", [(9, 9), (5, 5), (36, 36), (0x40 | 9, 9), (0x80 | 9, 9), (0xC0 | 9, 9)])
def test_a_printed_valid_count_is_taken_up_to_36_or_where_bits_7_6_explain_it(printed, n_valid):
    """The firmware prints the count byte whole; its bits 5:0 are the count (the register map's mask 0x3F). A value
    over 36 is taken when only bits 7:6 make it so: bits 5:0 count the pairs that hold a target (9 here). Up to 36
    the count is taken as printed (ams' Linux driver only logs a count that differs from the slots)."""
    obj = classify_line(chip_obj_line(printed), 0.0, 0x41)
    assert isinstance(obj, ResultPacket) and obj.n_valid == n_valid


@pytest.mark.parametrize("printed, why", [
    (37, "a #Obj line with 37 valid results, more than 36"),
    (100, "a #Obj line with 100 valid results, more than 36 (its bits 5:0 read 36, but 9 pairs hold a target)"),
    (0x40 | 8, "a #Obj line with 72 valid results, more than 36 (its bits 5:0 read 8, but 9 pairs hold a target)"),
    (255, "a #Obj line with 255 valid results, more than 36"),
])
def test_a_printed_valid_count_over_36_that_bits_7_6_do_not_explain_marks_a_corrupt_line(printed, why):
    """The bridge has no checksum: "100" (a garbled "10", say) must not read as 36 valid results."""
    assert classify_line(chip_obj_line(printed), 0.0, 0x41) == ("corrupt", why)


def test_of_the_printed_counts_over_36_only_those_bits_7_6_explain_pass():
    """Masking alone let 111 of the 219 values 37..255 through; with the pairs checked, three do (9 targets)."""
    taken = [v for v in range(37, 256) if isinstance(classify_line(chip_obj_line(v), 0.0, 0x41), ResultPacket)]
    assert taken == [0x40 | 9, 0x80 | 9, 0xC0 | 9]


# ---- 6. partial histograms -------------------------------------------------------------------------------------------
PRT_LINE = b"#Prt,65,3,0," + b",".join([b"7"] * 20)


def test_a_partial_histogram_line_says_the_bridge_is_in_partial_histogram_mode():
    kind, why = classify_line(PRT_LINE, 0.0, 0x41)
    assert kind == "partial_histogram" and "\n" not in why
    assert why.startswith("the bridge prints partial histograms (#Prt lines: its partial-histogram mode)")
    assert "30 #Raw lines of 128 bins per frame" in why


def test_partial_histograms_are_named_when_frames_stop(arun, caplog):
    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge) as sensor:
                bridge.send((PRT_LINE + b"\n") * 30 + b"#Obj\n")
                bridge.flush()
                deadline = time.monotonic() + 20
                while sensor.counters().get("partial_histogram_lines", 0) < 30:
                    assert time.monotonic() < deadline, f"the #Prt lines never counted: {sensor.counters()}"
                    await asyncio.sleep(0.01)
                with pytest.raises(SensorSilent) as silent:
                    await sensor.next_frame(0.05)
                return silent.value, sensor.counters()

    with caplog.at_level(logging.WARNING, logger="spadscan.daemon"):
        silent, c = arun(main())
    assert c["partial_histogram_lines"] == 30 and c["unknown_lines"] == 0 and c["bad_records"] == 30
    assert "the last one: the bridge prints partial histograms (#Prt lines: its partial-histogram mode)" in str(silent)
    assert "\n" not in str(silent)
    warned = [r.getMessage() for r in caplog.records if "partial histograms" in r.getMessage()]
    assert len(warned) == 1  # once, not for every line


# ---- 4. the accuracy mode ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("active_range, what", [(0x6F, "long range"), (0x00, "an application image without accuracy "
                                                                            "modes")])
def test_a_bridge_in_another_mode_than_short_range_is_refused_before_any_frame(arun, active_range, what):
    """The UW firmware prints the ACTIVE_RANGE it reads as it starts; the daemon cannot switch the bridge's mode,
    and long-range histograms stored under the tmf8820 model would misplace every surface: the frame that follows
    the line is never made, and the reason is one line."""
    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge) as sensor:
                bridge.boot(active_range)
                bridge.send_frame(counts(2), result(2))
                with pytest.raises(DeviceError) as info:
                    await sensor.next_frame(10)
                return str(info.value), sensor.counters()

    message, c = arun(main())
    assert "\n" not in message and c["frames"] == 0 and c["frames_delivered"] == 0
    printed = f"{active_range:X}"
    assert message.startswith("sensor serial ")
    assert message.endswith(
        f"reader stopped: the bridge firmware runs the sensor in {what} (Active range: {printed}), not short-range "
        f"high accuracy (6E), the only mode the tmf8820 sensor model describes, so no frame is stored: the daemon "
        f"cannot switch the bridge's mode, so build and flash a bridge firmware that sets short-range high accuracy "
        f"(command 0x6E after it downloads an ams application image with accuracy modes, before it measures, as the "
        f"UW firmware does), then reset the bridge and restart the daemon")
    assert c["active_range"] == {0x6F: "long range", 0x00: "no accuracy modes"}[active_range]


@pytest.mark.parametrize("booted", [False, True])
@pytest.mark.parametrize("printed", ["6", "E", "4E", "6C"])
def test_a_garbled_active_range_line_is_a_corrupt_line_and_frames_flow(arun, printed, booted):
    """With no checksum, a dropped or flipped character turns "6E" into a value ams documents no mode for: that is a
    corrupt line (counted, the mode left as it was), not a mode to refuse; before, it stopped the sensor until the
    daemon restarted. Only 6F and 0 are refused (above)."""
    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge) as sensor:
                if booted:
                    bridge.boot(0x6E)
                bridge.send(f"Active range: {printed}\n".encode())
                bridge.send_frame(counts(2), result(2))
                frame = await sensor.next_frame(10)
                return frame, sensor.counters()

    frame, c = arun(main())
    assert frame is not None and c["frames_delivered"] == 1
    assert c["corrupt_lines"] == 1 and c["bad_records"] == 1, c
    assert c["last_bad_record"] == (f"an Active range line with {printed}, no accuracy mode ams documents (6E, 6F or "
                                    f"0) ('Active range: {printed}')")
    assert c.get("active_range") == ("short range" if booted else None), c


# ---- 5. the bridge's start -------------------------------------------------------------------------------------------
def test_a_bridge_setting_its_sensor_up_again_says_its_start_may_last_until_its_first_record(arun):
    """After "FW downloaded" the UW firmware sends the short-range command and waits 4 s, calibrates, configures and
    starts measuring before its first record: the sensor says how long that may still take (the runner waits for it
    rather than pausing the scan as silent). Its "Active range" line does not end the start; the first record does."""
    async def main():
        with SimBridge() as bridge:
            async with streaming(bridge) as sensor:
                before = sensor.starting_left()
                bridge.boot(0x6E)
                deadline = time.monotonic() + 10
                while "active_range" not in sensor.counters() and time.monotonic() < deadline:
                    await asyncio.sleep(0.01)
                during, said = sensor.starting_left(), sensor.counters()
                bridge.send_frame(counts(2), result(2))
                await sensor.next_frame(10)
                return before, during, said, sensor.starting_left(), sensor.counters()

    before, during, said, after, c = arun(main())
    assert c["downloads"] == 1 and c["active_range"] == "short range", c
    assert before == 0 and after == 0
    assert BRIDGE_START_S - 5 < during <= BRIDGE_START_S
    assert abs(said["starting_s"] - during) < 1 and "starting_s" not in c  # in `ctl status` while it lasts
