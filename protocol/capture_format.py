"""The capture folder's data types and checks (docs/capture_format.md), shared by the writer and the reader.

```
CAPTURE/scan.json              manifest: sensor model, rig, hand-eye, schedule, state (running | complete | aborted)
CAPTURE/schedule.npy           optional planned sensor poses (P, 4, 4) float64, metres
CAPTURE/chunk-000000/          published chunks of at most `chunk_size` measurements, never changed once published
    hists.npy                  (n, zones, bins) uint32 photon counts
    poses.npy                  (n, 4, 4) float64 sensor-to-world, metres
    reference.npy              optional (n, bins) uint32 reference histograms
    meta.json                  {"measurements": [{"pose_index": int, "frame": int, ...}, ...]}
```
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.lib.format as npy_format

from .atomic_files import fsync_dir, write_durable
from .errors import CaptureError, ConfigError

FORMAT = "spadscan-capture"
VERSION = 1
MANIFEST = "scan.json"
SCHEDULE = "schedule.npy"
CHUNK_PREFIX = "chunk-"
TMP_PREFIX = ".tmp-"
STATES = ("running", "complete", "aborted")
POSE_TOL = 1e-4


@dataclass
class Measurement:
    """One histogram frame and where the sensor was.

    hist: (zones, bins) counts; pose: (4, 4) sensor-to-world (metres); reference: (bins,) or None; meta: JSON-able
    extras (timestamps s, temperature C, on-chip depths mm, joint angles rad, ...).
    """

    hist: np.ndarray
    pose: np.ndarray
    pose_index: int
    frame: int = 0
    reference: np.ndarray | None = None
    meta: dict = field(default_factory=dict)


@dataclass
class Chunk:
    """One published chunk, validated. Arrays as in the module docstring; `meta` is one dict per measurement."""

    name: str
    hists: np.ndarray
    poses: np.ndarray
    reference: np.ndarray | None
    meta: list[dict]

    @property
    def pose_indices(self) -> np.ndarray:
        return np.array([m["pose_index"] for m in self.meta], dtype=np.int64)


def drawn_by_simulator(manifest: dict) -> bool:
    """Whether a manifest's histograms were drawn by this project's simulator: `rig.kind` "simulated" (`spadscan
    simulate`) or `rig.sensor.backend` "sim" (the daemon's simulated sensor). Where they came from, whatever the scene
    says of how to fit them (`scene.real`). For a manifest the reader has checked (rig and rig.sensor objects)."""
    rig = manifest.get("rig") or {}
    return rig.get("kind") == "simulated" or (rig.get("sensor") or {}).get("backend") == "sim"


def chunk_name(index: int) -> str:
    return f"{CHUNK_PREFIX}{index:06d}"


CHUNK_NAME = re.compile(re.escape(CHUNK_PREFIX) + r"([0-9]{6})")
"""A published chunk's folder name: ASCII digits only (str.isdigit takes '١' and '²', and int('²') raises)."""


def chunk_index(name: str) -> int | None:
    """Index of a published chunk folder name, or None for anything else."""
    match = CHUNK_NAME.fullmatch(name)
    return int(match[1]) if match else None


def enclosing_capture(path) -> Path | None:
    """The capture folder (one holding MANIFEST) nearest above `path`, or `path` itself when it is one; None when
    none is, or where a folder on the way cannot be looked into. Paths resolved (a link into a capture is inside it):
    a command's --out there would put its files among that capture's measurements."""
    for folder in [Path(path).resolve(), *Path(path).resolve().parents]:
        try:
            if (folder / MANIFEST).is_file():
                return folder
        except OSError:
            return None
    return None


def check_new_capture_out(out) -> None:
    """Refuse (ConfigError, one line) an --out for a new capture that lies inside another capture's folder: its
    chunks and manifest would be mixed into that capture's measurements. One that is a capture itself is left to
    the writer, which says so."""
    around = enclosing_capture(out)
    if around is not None and around != Path(out).resolve():
        raise ConfigError(f"--out {out} lies inside the capture {around}: a capture there would be mixed into its "
                          f"measurements; choose a folder outside it")


def check_poses(poses: np.ndarray, where: str) -> np.ndarray:
    """Check (n, 4, 4) rigid transforms: finite, orthonormal rotation with det +1, last row (0, 0, 0, 1)."""
    poses = np.asarray(poses)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise CaptureError(f"{where}: poses have shape {poses.shape}, expected (n, 4, 4)")
    if not np.issubdtype(poses.dtype, np.floating):
        raise CaptureError(f"{where}: poses have dtype {poses.dtype}, expected float64")
    if not np.all(np.isfinite(poses)):
        bad = int(np.argwhere(~np.isfinite(poses).all(axis=(1, 2)))[0, 0])
        raise CaptureError(f"{where}: pose {bad} is not finite")
    r = poses[:, :3, :3]
    err = np.abs(np.einsum("nij,nkj->nik", r, r) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(r)
    last = np.abs(poses[:, 3] - np.array([0, 0, 0, 1.0])).max(axis=1)
    bad = np.flatnonzero((err > POSE_TOL) | (np.abs(det - 1) > POSE_TOL) | (last > POSE_TOL))
    if bad.size:
        i = int(bad[0])
        if last[i] > POSE_TOL:
            raise CaptureError(f"{where}: pose {i} has last row {poses[i, 3].tolist()}, expected [0, 0, 0, 1]")
        raise CaptureError(f"{where}: pose {i} is not rigid (|R R^T - I| = {err[i]:.2g}, det R = {det[i]:.4g})")
    return poses.astype(np.float64, copy=False)


def check_hists(hists: np.ndarray, zones: int, bins: int, where: str) -> np.ndarray:
    """Check (n, zones, bins) uint32 counts."""
    hists = np.asarray(hists)
    if hists.ndim != 3 or hists.shape[1:] != (zones, bins):
        raise CaptureError(f"{where}: histograms have shape {hists.shape}, expected (n, {zones}, {bins})")
    if hists.dtype != np.uint32:
        raise CaptureError(f"{where}: histograms have dtype {hists.dtype}, expected uint32")
    return hists


def to_counts(values: np.ndarray, where: str) -> np.ndarray:
    """Convert counts given as any numeric array to uint32, refusing negatives, NaN, fractions and overflow."""
    a = np.asarray(values)
    if a.dtype == np.uint32:
        return a
    if a.dtype.kind not in "iuf":
        raise CaptureError(f"{where}: counts have dtype {a.dtype}, expected numbers")
    if a.dtype.kind == "f":
        if not np.all(np.isfinite(a)):
            raise CaptureError(f"{where}: counts contain NaN or infinity")
        if np.any(a != np.round(a)):
            raise CaptureError(f"{where}: counts are not whole numbers")
    if a.size and (a.min() < 0 or a.max() > 2**32 - 1):
        raise CaptureError(f"{where}: counts outside 0..2^32-1 (min {a.min()}, max {a.max()})")
    return a.astype(np.uint32)


def fold(text) -> str:
    """Text on one line: each run of whitespace, line breaks included, becomes one space."""
    return " ".join(str(text).split())


def one_line(exc: BaseException) -> str:
    """An exception's message folded onto one line (library messages sometimes span several)."""
    return fold(exc) or type(exc).__name__


def strict_json(value):
    """A copy of `value` (dicts, lists, numbers, text) with every number that is not finite made None: JSON has no
    NaN or Infinity, and Python's json writes them as bare tokens that other readers refuse."""
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def check_json(data, where: str) -> None:
    """Refuse data that JSON cannot hold (objects, arrays), before anything is written."""
    try:
        json.dumps(data)
    except (TypeError, ValueError) as exc:
        raise CaptureError(f"{where}: not JSON-serialisable ({one_line(exc)})") from None


class NoPermission(CaptureError):
    """A capture file that this user may not read: its owner or mode stops it, not its content (a capture made or
    copied by another user). Never to be taken for a damaged file, whose advice (move it out) would lose good data."""


def no_permission(path) -> NoPermission:
    """The one line for a capture file this user may not read."""
    return NoPermission(f"{path}: cannot be read (permission denied: check the file's owner and mode; its content "
                        f"may be intact)")


def check_regular(path: Path) -> None:
    """OSError (EINVAL) where `path` is not a regular file (FileNotFoundError where it is missing). Asked before it is
    opened: a FIFO left where a file should be (or a device) would block a plain open until something writes to it,
    and with it a worker's whole look for scans."""
    mode = os.stat(path).st_mode
    if stat.S_ISDIR(mode):  # as open() says it
        raise IsADirectoryError(errno.EISDIR, "Is a directory", str(path))
    if not stat.S_ISREG(mode):
        raise OSError(errno.EINVAL, "not a regular file", str(path))


def read_json(path: Path) -> dict:
    """Read a JSON object; a missing, truncated or non-object file is a one-line CaptureError naming it (NoPermission
    for one this user may not read)."""
    try:
        check_regular(path)
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CaptureError(f"{path}: missing") from None
    except PermissionError:
        raise no_permission(path) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"{path}: unreadable JSON ({one_line(exc)})") from None
    except RecursionError:  # the parser recurses once per level of nesting
        raise CaptureError(f"{path}: unreadable JSON (nested too deeply)") from None
    if not isinstance(data, dict):
        raise CaptureError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


NPY_MAGIC = b"\x93NUMPY"


def read_npy(path: Path) -> np.ndarray:
    """Load a .npy file without pickles, in the machine's byte order; a file that is not a .npy, truncation or
    corruption is a one-line CaptureError naming the file (NoPermission for one this user may not read)."""
    try:
        check_regular(path)
        with open(path, "rb") as f:
            head = f.read(len(NPY_MAGIC))
            # Without the magic np.load would try to unpickle the file and complain about allow_pickle, which reads
            # as a pickling bug rather than a damaged file (zeroed after a power cut, text, an .npz archive).
            if head != NPY_MAGIC:
                raise CaptureError(f"{path}: " + ("corrupt or truncated .npy (it ends inside its header)"
                                                  if NPY_MAGIC.startswith(head) else
                                                  "not a .npy file (no .npy header: damaged, or another kind of "
                                                  "file)"))
            f.seek(0)
            problem = _npy_size_problem(f)
            if problem:
                raise CaptureError(f"{path}: corrupt or truncated .npy ({problem})")
            f.seek(0)
            array = np.load(f, allow_pickle=False)
    except FileNotFoundError:
        raise CaptureError(f"{path}: missing") from None
    except PermissionError:  # an OSError, but the file is not damaged: "corrupt" would point at the wrong fix
        raise no_permission(path) from None
    except IsADirectoryError:
        raise CaptureError(f"{path}: a folder, not a .npy file") from None
    except (OSError, ValueError, EOFError) as exc:
        if "allow_pickle" in str(exc):  # numpy's own advice there (load it unsafely) is no advice for a capture
            raise CaptureError(f"{path}: holds Python objects, not a plain array; a capture never writes such a "
                               f"file") from None
        raise CaptureError(f"{path}: corrupt or truncated .npy ({one_line(exc)})") from None
    if not array.dtype.isnative:
        # A big-endian file (another writer, another machine) holds the same numbers: compare and compute natively.
        array = array.astype(array.dtype.newbyteorder("="))
    return array


def _npy_size_problem(f) -> str | None:
    """Why an open .npy file (at its start) cannot hold the array its header describes, or None (also for a
    header this cannot read: np.load says what is wrong with it then). A damaged header can claim any shape: numpy
    would try to allocate it before reading a byte of the data."""
    try:
        version = npy_format.read_magic(f)
        read_header = {(1, 0): npy_format.read_array_header_1_0,
                       (2, 0): npy_format.read_array_header_2_0}.get(version)
        if read_header is None:
            return None
        shape, _, dtype = read_header(f)
    except (ValueError, OSError, EOFError):
        return None
    if dtype.hasobject:
        return None
    expected = math.prod(shape) * dtype.itemsize
    held = os.fstat(f.fileno()).st_size - f.tell()
    if held != expected:
        return f"its header describes {shape} {dtype} ({expected:,} bytes of data), the file holds {held:,}"
    return None


def npy_is_whole(path: Path) -> bool:
    """Whether the .npy file at `path` holds as many bytes as its header describes (False when it cannot be read):
    a file still being copied in is short of them."""
    try:
        check_regular(path)
        with open(path, "rb") as f:
            if f.read(len(NPY_MAGIC)) != NPY_MAGIC:
                return False
            f.seek(0)
            return _npy_size_problem(f) is None
    except OSError:
        return False


def save_npy_durable(path: Path, array: np.ndarray) -> None:
    """`array` as .npy at `path`, on the disk when this returns. A write the kernel cut short raises numpy's short
    write ("N requested and M written", no errno: `disk_full.is_short_write`) also where numpy said nothing: it writes
    through C stdio, and a failure to flush the last partial buffer (at the file-size limit, on a disk that filled in
    the file's last kilobytes) it never raises. Such a file, short of what its header says, was published as a chunk,
    and the scan ended complete with every chunk unreadable."""
    with open(path, "wb") as f:
        np.save(f, array, allow_pickle=False)
        f.flush()
        os.fsync(f.fileno())
        due, written = f.tell(), os.fstat(f.fileno()).st_size
    if written != due or written < array.nbytes:
        raise OSError(f"{max(due, array.nbytes)} requested and {written} written")


def write_json_atomic(path: Path, data: dict) -> None:
    """Replace a JSON file atomically: temp file, fsync, rename, fsync the folder."""
    path = Path(path)
    tmp = path.with_name(f"{TMP_PREFIX}{path.name}")
    write_durable(tmp, (json.dumps(data, indent=1) + "\n").encode())
    os.replace(tmp, path)
    fsync_dir(path.parent)
