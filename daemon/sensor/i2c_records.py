"""The records a TMF8820 application publishes at register 0x20: histogram sub-packets and measurement results.

Every record starts with a 4-byte header: RID (what the record is), TID (changes with every record), size (u16 LE).

- A raw 24-bit histogram (RID 0x81: bit 7 says a sub-packet header follows) is one message of 10 channels x
  3 byte planes x 128 bins sent as 30 sub-packets of 135 bytes: header, sub-header (sub-packet number 0..29, payload
  length 128, config id), 128 payload bytes. The header's size field counts the message still to come *without*
  the sub-packet headers (ams' host-interface protocol: the size written excludes the sub-packet headers): 3840
  (30 x 128) in sub-packet 0, 128 less in each sub-packet after it. Sub-packet n holds byte plane n // 10 of
  channel n % 10 (assembled in `assembly`).
  A sub-packet is taken on what ams' drivers rely on: RID, sub-packet number (where it goes) and the sub-header's
  payload length (ams' Linux driver copies that many bytes; every driver reads 4 + 3 + 128 bytes). None of them
  checks the size field of a later sub-packet (the Linux driver takes the message size from sub-packet 0 only), so a
  firmware may write it otherwise (the total in every sub-packet, say): such a sub-packet is still taken, and the
  disagreement is only reported (`size_field_disagreement`).
- A measurement result (RID 0x10) is 132 bytes: header (size 128), result number, temperature (deg C, an unsigned
  byte: ams' Python driver declares it uint8, its Linux driver decodes it as one, its Arduino driver prints it as
  0..255), number of valid results (bits 5:0: the register map's mask 0x3F for NUMBER_VALID_RESULTS 0x26; what bits
  7:6 mean it does not say, and ams' drivers read the whole byte), reserved, ambient light u32, photon count u32,
  reference photon count u32, system ticks u32, then 36 result slots {confidence u8, distance mm u16 LE}.
  Slot k is target (k // 18) + 1 of channel (k % 9) + 1 in sub-capture (k // 9) % 2 (ams' Linux driver's
  RESULT_IDX_TO_CHANNEL / RESULT_IDX_TO_SUB_CAPTURE; its Python driver's object1[0..17], object2[0..17]): with one
  SPAD map (no time multiplexing, as the daemon configures) slots 0-8 are the first target of channels 1-9, slots
  18-26 their second target, and slots 9-17 and 27-35 (sub-capture 1) stay 0. A slot without a target reads
  confidence 0 and distance 0 (`slot_target` says what slot k holds). The distances are stored as the chip wrote
  them: no clock correction (ams' Arduino driver, and the bridge firmware built on it, print corrected ones).
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


VALID_RESULTS_MASK = 0x3F
"""NUMBER_VALID_RESULTS (result byte 6, register 0x26) is a 6-bit field (ams' register map)."""
N_TARGETS, N_SUB_CAPTURES, N_ZONE_CHANNELS = 2, 2, 9


def valid_results(byte: int) -> int:
    """The number of valid results a result's count byte holds: its bits 5:0."""
    return byte & VALID_RESULTS_MASK


def slot_target(k: int) -> tuple[int, int, int]:
    """What result slot k (0..35) holds: (channel 1..9, sub-capture 0..1, target 1..2). Capture zone index = channel
    - 1 (channel 0 is the reference, which has no result slot)."""
    if not 0 <= k < N_RESULTS:
        raise ValueError(f"result slot {k} is not in 0..{N_RESULTS - 1}")
    return k % N_ZONE_CHANNELS + 1, (k // N_ZONE_CHANNELS) % N_SUB_CAPTURES, k // (N_ZONE_CHANNELS * N_TARGETS) + 1


def histogram_refusal(buf: bytes) -> str:
    """Why `buf` is not a raw histogram sub-packet that can be placed in a frame, or '' when it is one.

    The size field is not looked at (see the module docstring): `size_field_disagreement` reports it.
    """
    if len(buf) != HIST_RECORD:
        return f"{len(buf)} bytes, not {HIST_RECORD}"
    if buf[0] != RID_RAW_HISTOGRAM:
        return f"RID {buf[0]:#04x}, not {RID_RAW_HISTOGRAM:#04x} (raw 24-bit histogram)"
    if buf[4] >= N_SUBPACKETS:
        return f"sub-packet number {buf[4]}, not 0..{N_SUBPACKETS - 1}"
    if buf[5] != SUBPACKET_BYTES:
        return f"sub-packet payload length {buf[5]}, not {SUBPACKET_BYTES} (one byte plane of 128 bins)"
    return ""


def size_field_disagreement(buf: bytes) -> str:
    """How the size field of histogram sub-packet `buf` differs from the documented one, or '' when it agrees."""
    index, size = buf[4], buf[2] | buf[3] << 8
    if size == remaining_size(index):
        return ""
    return f"sub-packet {index} has size field {size}, the protocol documents {remaining_size(index)}"


def result_refusal(buf: bytes) -> str:
    """Why `buf` is not a measurement result, or '' when it is one."""
    if len(buf) != RESULT_RECORD:
        return f"{len(buf)} bytes, not {RESULT_RECORD}"
    if buf[0] != RID_RESULT:
        return f"RID {buf[0]:#04x}, not {RID_RESULT:#04x} (measurement result)"
    # ams' Linux driver reads a larger size as extra data after the 36 results (the diagnostics the register map
    # places at 0xA4-0xC7): the results themselves stand where they do, so only a shorter record is refused.
    if buf[2] | buf[3] << 8 < RESULT_RECORD - HEADER_BYTES:
        return f"size field {buf[2] | buf[3] << 8}, under {RESULT_RECORD - HEADER_BYTES}"
    if valid_results(buf[6]) > N_RESULTS:
        return f"{valid_results(buf[6])} valid results (count byte {buf[6]:#04x}), more than {N_RESULTS}"
    return ""


def parse_histogram_record(buf: bytes, t: float) -> HistogramPacket | None:
    """A 135-byte histogram sub-packet, or None when `histogram_refusal` refuses it (`t`: arrival, s)."""
    if histogram_refusal(buf):
        return None
    return HistogramPacket(index=buf[4], payload=bytes(buf[HEADER_BYTES + SUBHEADER_BYTES:]), t=t)


def parse_result_record(buf: bytes, t: float) -> ResultPacket | None:
    """A 132-byte measurement result, or None when `result_refusal` refuses it (`t`: arrival, s)."""
    if result_refusal(buf):
        return None
    u32 = [int.from_bytes(buf[k:k + 4], "little") for k in (8, 12, 16, 20)]
    body = buf[24:]
    return ResultPacket(result_no=buf[4], temperature_c=float(buf[5]), n_valid=valid_results(buf[6]), systick=u32[3],
                        distances_mm=[body[3 * k + 1] | body[3 * k + 2] << 8 for k in range(N_RESULTS)],
                        confidences=[body[3 * k] for k in range(N_RESULTS)], t=t,
                        extra={"ambient": u32[0], "photon_count": u32[1], "reference_count": u32[2]})
