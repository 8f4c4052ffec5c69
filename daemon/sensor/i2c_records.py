"""The records a TMF8820 application publishes at register 0x20: histogram sub-packets and measurement results.

Every record starts with a 4-byte header: RID (what the record is), TID (changes with every record), size (u16 LE).

- A raw 24-bit histogram (RID 0x81: bit 7 says a sub-packet header follows) is one message of 10 channels x
  3 byte planes x 128 bins sent as 30 sub-packets of 135 bytes: header, sub-header (sub-packet number 0..29, payload
  length 128, config id), 128 payload bytes. The header's size field counts the message still to come *without*
  the sub-packet headers (ams' host-interface protocol: the size written excludes the sub-packet headers): 3840
  (30 x 128) in sub-packet 0, 128 less in each sub-packet after it. Sub-packet n holds byte plane n // 10 of
  channel n % 10 (assembled in `assembly`).
- A measurement result (RID 0x10) is 132 bytes: header (size 128), result number, temperature (deg C, a signed byte;
  the references read it as unsigned), number of valid results, reserved, ambient light u32, photon count u32,
  reference photon count u32, system ticks u32, then 36 x {confidence u8, distance mm u16 LE}.
"""

from __future__ import annotations

from .transport import N_RESULTS, N_SUBPACKETS, SUBPACKET_BYTES, HistogramPacket, ResultPacket

RID_RAW_HISTOGRAM, RID_RESULT = 0x81, 0x10
HEADER_BYTES, SUBHEADER_BYTES = 4, 3
HIST_RECORD = HEADER_BYTES + SUBHEADER_BYTES + SUBPACKET_BYTES  # 135 bytes
RESULT_RECORD = HEADER_BYTES + 20 + 3 * N_RESULTS  # 132 bytes
HISTOGRAM_MESSAGE_BYTES = N_SUBPACKETS * SUBPACKET_BYTES  # 3840: the size field of sub-packet 0


def remaining_size(index: int) -> int:
    """The size field of histogram sub-packet `index`: message bytes from this sub-packet on, sub-headers excluded."""
    return (N_SUBPACKETS - index) * SUBPACKET_BYTES


def signed_byte(value: int) -> int:
    """A byte that carries a two's complement number (the temperature) as an int in [-128, 127]."""
    return value - 256 if value > 127 else value


def parse_histogram_record(buf: bytes, t: float) -> HistogramPacket | None:
    """A 135-byte histogram sub-packet, or None when its header or sub-header is not one (`t`: arrival, s)."""
    if len(buf) != HIST_RECORD or buf[0] != RID_RAW_HISTOGRAM:
        return None
    index, size = buf[4], buf[2] | buf[3] << 8
    if index >= N_SUBPACKETS or size != remaining_size(index) or buf[5] != SUBPACKET_BYTES:
        return None
    return HistogramPacket(index=index, payload=bytes(buf[HEADER_BYTES + SUBHEADER_BYTES:]), t=t)


def parse_result_record(buf: bytes, t: float) -> ResultPacket | None:
    """A 132-byte measurement result, or None when its header is not one (`t`: arrival, s)."""
    if (len(buf) != RESULT_RECORD or buf[0] != RID_RESULT or buf[2] | buf[3] << 8 != RESULT_RECORD - HEADER_BYTES
            or buf[6] > N_RESULTS):
        return None
    u32 = [int.from_bytes(buf[k:k + 4], "little") for k in (8, 12, 16, 20)]
    body = buf[24:]
    return ResultPacket(result_no=buf[4], temperature_c=float(signed_byte(buf[5])), n_valid=buf[6], systick=u32[3],
                        distances_mm=[body[3 * k + 1] | body[3 * k + 2] << 8 for k in range(N_RESULTS)],
                        confidences=[body[3 * k] for k in range(N_RESULTS)], t=t,
                        extra={"ambient": u32[0], "photon_count": u32[1], "reference_count": u32[2]})
