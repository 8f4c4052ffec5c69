"""The TMF8820 application image (the user's own copy; ams does not allow shipping it) and bootloader frames.

The image is lost at every power loss and is downloaded into the sensor's RAM by the bootloader. Files ending in
`.hex` are read as Intel HEX (data, end-of-file and extended-address records); any other file is a raw binary image
loaded at `load_address`. A bootloader frame written to register 0x08 is `[cmd, len, payload..., checksum]` with
checksum = ~(cmd + len + sum(payload)) & 0xFF.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from spadscan.protocol.errors import DeviceError

BL_DOWNLOAD_INIT = 0x14
DOWNLOAD_SEED = 0x29
"""DOWNLOAD_INIT's one payload byte: the seed ams' C host driver (its Linux driver, and SparkFun's Arduino library,
which is built on it) sends before any SET_ADDR for its encrypted images. ams' own Arduino and Python drivers leave
the command out and start with SET_ADDR; the bootloader takes the same image either way, so it is always sent."""
BL_SET_ADDR = 0x43
BL_W_RAM = 0x41
BL_RAMREMAP = 0x11
BL_CHUNK = 128
"""Most payload bytes in one W_RAM frame."""


@dataclass(frozen=True)
class FirmwareImage:
    """Where the image goes: segments of (RAM address, bytes), in file order."""

    path: Path
    segments: tuple[tuple[int, bytes], ...]

    @property
    def size(self) -> int:
        return sum(len(data) for _, data in self.segments)


def load_firmware(path: str | Path, load_address: int = 0) -> FirmwareImage:
    """Read the image at `path`; a missing, unreadable, empty or malformed file is a one-line DeviceError."""
    path = Path(path).expanduser()
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise DeviceError(f"TMF8820 firmware image {path} does not exist (point `firmware` at your copy of the "
                          "ams application image)") from None
    except IsADirectoryError:
        raise DeviceError(f"TMF8820 firmware image {path} is a folder, not a file (point `firmware` at the image "
                          "inside it)") from None
    except OSError as exc:
        raise DeviceError(f"TMF8820 firmware image {path} cannot be read: {exc.strerror}") from None
    if not raw:
        raise DeviceError(f"TMF8820 firmware image {path} is empty")
    # By content, not by name alone: ams' HEX image saved as .ihex or .hex.txt was written byte for byte, its text
    # (20 kB of ASCII) into the chip's RAM, and the only error was the application not starting.
    if path.suffix.lower() == ".hex" or raw.lstrip().startswith(b":"):
        segments = parse_intel_hex(raw, path)
    elif _is_text(raw):
        raise DeviceError(f"TMF8820 firmware image {path} is text, neither Intel HEX (lines starting with ':') nor a "
                          f"raw binary image")
    else:
        segments = ((load_address & 0xFFFF, raw),)
    return FirmwareImage(path, segments)


def _is_text(raw: bytes) -> bool:
    """Whether `raw` is all printable ASCII and line breaks (a binary image never is: its code bytes span 0-255)."""
    return all(32 <= b < 127 or b in b"\r\n\t" for b in raw)


def parse_intel_hex(raw: bytes, where: Path) -> tuple[tuple[int, bytes], ...]:
    """Segments (address low 16 bits, data) of contiguous data records; checks every record's checksum."""
    segments: list[tuple[int, bytearray]] = []
    base = 0
    for no, line in enumerate(raw.decode("ascii", "replace").splitlines(), 1):
        line = line.strip()
        if not line:
            continue
        try:
            if not line.startswith(":"):
                raise ValueError("no ':'")
            rec = bytes.fromhex(line[1:])
            if len(rec) < 5 or len(rec) != rec[0] + 5 or sum(rec) & 0xFF:
                raise ValueError("bad length or checksum")
        except ValueError as exc:
            raise DeviceError(f"TMF8820 firmware image {where}: line {no} is not an Intel HEX record ({exc})") from None
        count, addr, kind, data = rec[0], (rec[1] << 8) | rec[2], rec[3], rec[4:-1]
        if kind == 0x00:
            full = base + addr
            if segments and segments[-1][0] + len(segments[-1][1]) == full:
                segments[-1][1].extend(data)
            else:
                segments.append((full, bytearray(data)))
        elif kind == 0x01:
            break
        elif kind == 0x04 and count == 2:
            base = ((data[0] << 8) | data[1]) << 16
        elif kind == 0x02 and count == 2:
            base = ((data[0] << 8) | data[1]) << 4  # extended segment address: the data that follows goes there
        elif kind in (0x03, 0x05):
            continue  # start addresses: where a CPU would jump, not where data goes; RAMREMAP starts the image
        else:
            raise DeviceError(f"TMF8820 firmware image {where}: line {no} has unsupported record type {kind:#04x}")
    if not segments:
        raise DeviceError(f"TMF8820 firmware image {where}: no data records")
    return tuple((a & 0xFFFF, bytes(d)) for a, d in segments)


def checksum(body: bytes) -> int:
    """Bootloader checksum: ones' complement of the byte sum of cmd, len and payload."""
    return ~sum(body) & 0xFF


def bootloader_frame(cmd: int, payload: bytes = b"") -> bytes:
    """`[cmd, len, payload..., checksum]` (the register byte 0x08 is prepended by the bus write)."""
    if len(payload) > BL_CHUNK:
        raise ValueError(f"bootloader payload of {len(payload)} bytes exceeds {BL_CHUNK}")
    body = bytes([cmd, len(payload)]) + bytes(payload)
    return body + bytes([checksum(body)])


def download_frames(image: FirmwareImage) -> list[tuple[str, bytes]]:
    """The bootloader frames that put `image` into RAM, each with a label for errors: DOWNLOAD_INIT first, RAMREMAP
    last."""
    frames = [("DOWNLOAD_INIT", bootloader_frame(BL_DOWNLOAD_INIT, bytes([DOWNLOAD_SEED])))]
    for addr, data in image.segments:
        frames.append((f"SET_ADDR {addr:#06x}", bootloader_frame(BL_SET_ADDR, bytes([addr & 0xFF, addr >> 8]))))
        for off in range(0, len(data), BL_CHUNK):
            frames.append((f"W_RAM at {addr + off:#06x}", bootloader_frame(BL_W_RAM, data[off:off + BL_CHUNK])))
    frames.append(("RAMREMAP", bootloader_frame(BL_RAMREMAP)))
    return frames
