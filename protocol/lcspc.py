"""Reading the public LCSPCData format (CVPR 2024, MIT licence) and converting it into capture folders.

A file is a JSON list of measurements. Two kinds exist, told apart by the shape of `hists` (never by the file name):

- simulated: `{"hists": [1024 counts], "pose": 4x4}` -> sensor preset `lcspc-sim`, one zone;
- real (ams TMF8820 on a UR arm): `{"hists": 9 x 128, "reference_hist": 128, "pose": 4x4, "joint_angles": 6,
  "distances": [{on-chip depths mm, confidences, temperature C, tick, ...}], "time_captured": ...}`
  -> sensor preset `tmf8820`, nine zones in the sensor's channel order, the reference histogram kept.

Poses are sensor-to-world in metres with the sensor looking along +z, as in spadscan; a pose stored with the last row
[0, 0, 0, 0] (some real captures do) is read as the rigid transform it is when its 3x3 block is a rotation, with a
warning; poses spread far wider than the sensor can range (millimetres, most likely) are refused. Every key other
than `hists`, `pose` and `reference_hist` is kept verbatim in the measurement's metadata, plus `source_index` (the
position in the file) and `temperature_c` when the on-chip record gives one.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .capture_format import POSE_TOL, Measurement, check_poses
from .errors import CaptureError, DatasetError
from .sensor_model import SensorModel
from .sensor_presets import sensor_preset

# kind -> sensor preset; the preset's (zones, bins) is what identifies the kind in the data
KINDS = {"simulated": "lcspc-sim", "real": "tmf8820"}
RESERVED = ("hists", "pose", "reference_hist")
READ_BLOCK = 1 << 20
SPREAD_RANGES = 4
"""Sensor positions may lie at most this many of the sensor's ranges (max_range_m) from their centroid. Each view
measures surfaces within one range R of itself, so views of an object of radius r lie within R + r of its centre and
within 2 (R + r) of their centroid; r <= R (a lab scanner's objects; the dataset's are ~0.25 m) gives 4 R. The
dataset's scenes reach 0.12-0.44 R (simulated: 0.56 m of 1.28 m; real, upstream's bust and tall_block included:
0.20-0.36 m of 1.57 m), and the same poses in millimetres would be 120-440 R."""

Progress = Callable[[str, int, int], None]
"""progress(stage, done, total): stage 'read' counts bytes of the file, stage 'write' counts measurements."""


@dataclass
class LcspcData:
    """One LCSPCData file, validated. hists (N, zones, bins) uint32; poses (N, 4, 4) float64 metres, sensor-to-world;
    reference (N, bins) uint32 or None; meta: one JSON-able dict per measurement."""

    source: Path
    kind: str
    sensor: SensorModel
    hists: np.ndarray
    poses: np.ndarray
    reference: np.ndarray | None
    meta: list[dict]
    sha256: str
    notes: tuple[str, ...] = ()
    """What was read but not kept as given (one line each), for the user to see."""
    warnings: tuple[str, ...] = ()
    """What was malformed in the file but repaired without doubt (one line each), for the user to see."""


def read_lcspc(path, progress: Progress | None = None) -> LcspcData:
    """Read and validate an LCSPCData JSON file. Every problem is a one-line DatasetError naming the file."""
    path = Path(path)
    raw, digest = _read_bytes(path, progress)
    try:
        records = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({' '.join(str(exc).split())})") from None
    if not isinstance(records, list):
        raise DatasetError(f"{path}: expected a JSON list of measurements, got a {type(records).__name__}")
    if not records:
        raise DatasetError(f"{path}: holds no measurements")
    for i, rec in enumerate(records):
        if not isinstance(rec, dict):
            raise DatasetError(f"{path}: measurement {i} is a {type(rec).__name__}, expected an object")
        for key in ("hists", "pose"):
            if key not in rec:
                raise DatasetError(f"{path}: measurement {i} lacks {key!r}")
    kind, sensor = detect_kind(path, records[0]["hists"])
    shape = (sensor.n_zones, sensor.n_bins)
    hists = np.stack([_array(path, i, "hists", r["hists"], shape) for i, r in enumerate(records)])
    hists = _counts(path, "hists", hists, sensor.max_count)
    poses = np.stack([_array(path, i, "pose", r["pose"], (4, 4)) for i, r in enumerate(records)])
    poses, warnings = _complete_last_rows(path, poses.astype(np.float64))
    try:
        poses = check_poses(poses, str(path))
    except CaptureError as exc:
        raise DatasetError(str(exc)) from None
    _check_spread(path, poses, sensor)
    reference = _references(path, records, sensor)
    meta = [_meta(path, i, r) for i, r in enumerate(records)]
    return LcspcData(path, kind, sensor, hists, poses, reference, meta, digest, _temperature_notes(records),
                     warnings)


def detect_kind(path, hists) -> tuple[str, SensorModel]:
    """('simulated' | 'real', sensor preset) from the shape of one measurement's `hists`."""
    shape = _as_array(path, 0, "hists", hists).shape
    for kind, preset in KINDS.items():
        sensor = sensor_preset(preset)
        if shape == (sensor.n_zones, sensor.n_bins) or (sensor.n_zones == 1 and shape == (sensor.n_bins,)):
            return kind, sensor
    raise DatasetError(f"{path}: measurement 0 has hists of shape {shape}; expected (1024,) (simulated, "
                       f"lcspc-sim) or (9, 128) (real TMF8820)")


def ground_truth_for(path, kind: str) -> Path | None:
    """The ground-truth mesh beside a scene file: `<scene>.obj` (or .stl/.ply) of the same name, else for real
    scenes the only `*.stl` in the folder (LCSPCData names it after the object, not the capture)."""
    path = Path(path)
    for suffix in (".obj", ".stl", ".ply"):
        if path.with_suffix(suffix).is_file():
            return path.with_suffix(suffix)
    if kind == "real":
        stls = sorted(p for p in path.parent.glob("*.stl") if p.is_file())
        if len(stls) == 1:
            return stls[0]
    return None


def import_lcspc(path, out, *, chunk_size: int = 64, scan_id: str | None = None,
                 progress: Progress | None = None) -> "ImportSummary":
    """Convert an LCSPCData file into a complete capture folder `out` (which must not hold a capture yet).

    Validates the whole file before creating anything, so a bad file leaves no half capture behind.
    """
    from .capture_writer import CaptureWriter

    data = read_lcspc(path, progress)
    gt = ground_truth_for(data.source, data.kind)
    scene = {"dataset": "LCSPCData", "source": str(data.source.resolve()), "source_sha256": data.sha256,
             "kind": data.kind, "name": data.source.stem, "measurements": len(data.meta)}
    if gt is not None:
        scene["ground_truth"] = str(gt.resolve())
    if data.warnings:
        scene["import_warnings"] = list(data.warnings)
    writer = CaptureWriter.create(out, data.sensor, scan_id=scan_id, chunk_size=chunk_size, scene=scene,
                                  planned_poses=data.poses, schedule={"kind": "lcspc", "views": len(data.meta)})
    n = len(data.meta)
    try:
        for i in range(n):
            ref = None if data.reference is None else data.reference[i]
            writer.append(Measurement(data.hists[i], data.poses[i], pose_index=i, reference=ref, meta=data.meta[i]))
            if progress is not None:
                progress("write", i + 1, n)
        writer.finish()
    except BaseException as exc:
        writer.abandon("import", exc)
        raise
    chunks = -(-n // chunk_size)
    return ImportSummary(Path(out), data.kind, data.sensor.name, n, tuple(data.hists.shape),
                         None if data.reference is None else tuple(data.reference.shape), chunks, gt, data.notes,
                         data.warnings)


@dataclass
class ImportSummary:
    """What `import_lcspc` wrote: the capture folder, the detected kind and preset, the array shapes."""

    out: Path
    kind: str
    sensor: str
    measurements: int
    hists_shape: tuple[int, ...]
    reference_shape: tuple[int, ...] | None
    chunks: int
    ground_truth: Path | None
    notes: tuple[str, ...] = ()
    """What was read but not kept as given (LcspcData.notes)."""
    warnings: tuple[str, ...] = ()
    """What was malformed but repaired (LcspcData.warnings)."""


# ---- helpers ---------------------------------------------------------------------------------------------------------
# what a path is when it is not a regular file, for the one-line refusal
NOT_FILES = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a pipe"), (stat.S_ISCHR, "a device"),
             (stat.S_ISBLK, "a device"), (stat.S_ISSOCK, "a socket"))


def _read_bytes(path: Path, progress: Progress | None) -> tuple[bytes, str]:
    try:
        mode = path.stat().st_mode
    except (FileNotFoundError, NotADirectoryError):
        raise DatasetError(f"{path}: no such LCSPCData JSON file") from None
    if not stat.S_ISREG(mode):
        # A pipe (`<(zcat ...)`) could be read, but the capture records the source's path and looks for the ground
        # truth beside it, and a pipe's path names neither: ask for the file itself.
        what = next((name for test, name in NOT_FILES if test(mode)), "not a regular file")
        raise DatasetError(f"{path}: is {what}, not an LCSPCData JSON file; give the JSON file's own path")
    total = path.stat().st_size
    parts, done, digest = [], 0, hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(READ_BLOCK):
            parts.append(block)
            digest.update(block)
            done += len(block)
            if progress is not None:
                progress("read", done, total)
    return b"".join(parts), digest.hexdigest()


def _as_array(path, i: int, key: str, value) -> np.ndarray:
    """One measurement's nested JSON lists as an array; ragged lists, true/false and integers beyond 64 bits are
    one-line DatasetErrors (other non-numbers give a string or object dtype, left to `_array`)."""
    try:
        a = np.asarray(value)
    except ValueError:  # nested lists of different lengths
        raise DatasetError(f"{path}: measurement {i} has a ragged or non-numeric {key!r}") from None
    # numpy turns true/false among numbers into 1/0 without a trace, and keeps integers beyond 64 bits as Python
    # objects: only the JSON values themselves tell (not ragged here, so they lie exactly a.ndim lists deep)
    types = set(map(type, _leaves(value, a.ndim)))
    if bool in types:
        raise DatasetError(f"{path}: measurement {i} has non-numeric {key} (true or false among its numbers)")
    if a.dtype == object and int in types:
        big = next((v for v in _leaves(value, a.ndim) if type(v) is int and not -2**63 <= v < 2**64), None)
        if big is not None:
            raise DatasetError(f"{path}: measurement {i} has a number too large in {key} ({_clip(str(big))}, "
                               f"beyond 64 bits)")
    return a


def _leaves(value, depth: int):
    """The items of nested lists `depth` lists deep (value itself when depth is 0)."""
    leaves = [value]
    for _ in range(depth):
        leaves = itertools.chain.from_iterable(leaves)
    return leaves


def _array(path, i: int, key: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """One measurement's array, reshaped to `shape` (a flat single-zone histogram gains its zone axis)."""
    a = _as_array(path, i, key, value)
    got = a.shape
    if got != shape and not (got == shape[1:] and shape[0] == 1):
        want = shape[1:] if len(shape) == 2 and shape[0] == 1 else shape
        raise DatasetError(f"{path}: measurement {i} has {key} of shape {got}, expected {want}"
                           + (" (mixed kinds in one file?)" if key == "hists" else ""))
    if a.dtype.kind not in "iuf":  # strings, null, objects
        raise DatasetError(f"{path}: measurement {i} has non-numeric {key} ({a.dtype})")
    return a.reshape(shape)


def _counts(path, key: str, a: np.ndarray, max_count: int) -> np.ndarray:
    """(N, ...) counts -> uint32, naming the first measurement that is non-finite, negative, fractional or too big."""
    flat = a.reshape(len(a), -1)
    checks = [(~np.isfinite(flat), "non-finite"), (flat < 0, "negative"), (flat > max_count, f"> {max_count}")]
    if a.dtype.kind == "f":
        checks.append((np.isfinite(flat) & (flat != np.round(flat)), "fractional"))
    for bad, what in checks:
        rows = np.flatnonzero(bad.any(axis=1))
        if rows.size:
            i = int(rows[0])
            raise DatasetError(f"{path}: measurement {i} has {what} counts in {key} "
                               f"(min {flat[i].min()}, max {flat[i].max()})")
    return a.astype(np.uint32)


def _references(path, records: list[dict], sensor: SensorModel) -> np.ndarray | None:
    has = [("reference_hist" in r) for r in records]
    if not any(has):
        return None
    if not sensor.has_reference:
        raise DatasetError(f"{path}: measurement {has.index(True)} has a reference_hist, which the "
                           f"{sensor.name} sensor does not produce")
    if not all(has):
        raise DatasetError(f"{path}: measurement {has.index(False)} lacks the reference_hist the others have")
    refs = np.stack([_array(path, i, "reference_hist", r["reference_hist"], (sensor.n_bins,))
                     for i, r in enumerate(records)])
    return _counts(path, "reference_hist", refs, sensor.max_count)


def _meta(path, i: int, rec: dict) -> dict:
    """Everything but the arrays, verbatim; the writer's own keys are renamed rather than overwritten."""
    meta = {"source_index": i}
    for key, value in rec.items():
        if key in RESERVED:
            continue
        meta[f"source_{key}" if key in ("pose_index", "frame", "source_index") else key] = value
    if "joint_angles" in rec:
        q = rec["joint_angles"]
        ok = isinstance(q, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in q)
        if not ok or len(q) != 6 or not np.all(np.isfinite(q)):
            raise DatasetError(f"{path}: measurement {i} has joint_angles {str(q)[:80]}, expected 6 finite numbers")
    celsius = _temperature(rec)[1]
    if celsius is not None:
        meta["temperature_c"] = celsius
    return meta


def _complete_last_rows(path, poses: np.ndarray) -> tuple[np.ndarray, tuple[str, ...]]:
    """Poses (N, 4, 4) whose last row is [0, 0, 0, 0] (some real captures store every pose so) get [0, 0, 0, 1]: the
    last row of any rigid transform, so nothing is guessed when the 3x3 block is a rotation. Such a pose whose block
    is not a rotation is a one-line DatasetError; every other pose is left for `check_poses`. Returns the poses and
    a warning line when any was completed."""
    # a pose that is not finite is left for check_poses to name; its det would print a numpy warning first
    zero_last = np.isfinite(poses).all(axis=(1, 2)) & np.all(np.abs(poses[:, 3]) <= POSE_TOL, axis=1)
    if not zero_last.any():
        return poses, ()
    rot = poses[zero_last, :3, :3]
    err = np.abs(np.einsum("nij,nkj->nik", rot, rot) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rot)
    bad = np.flatnonzero((err > POSE_TOL) | (np.abs(det - 1) > POSE_TOL))
    if bad.size:
        i, k = int(np.flatnonzero(zero_last)[bad[0]]), int(bad[0])
        raise DatasetError(f"{path}: pose {i} has last row [0, 0, 0, 0] and a 3x3 block that is not a rotation "
                           f"(|R R^T - I| = {err[k]:.2g}, det R = {det[k]:.4g})")
    poses = poses.copy()
    poses[zero_last, 3] = (0.0, 0.0, 0.0, 1.0)
    n, first = int(zero_last.sum()), int(np.argmax(zero_last))
    which = f"all {n} poses have" if n == len(poses) else f"{n} of {len(poses)} poses (first: pose {first}) have"
    return poses, (f"{which} last row [0, 0, 0, 0]; read as [0, 0, 0, 1], the last row of every rigid transform "
                   f"(their rotations and translations are valid)",)


def _check_spread(path, poses: np.ndarray, sensor: SensorModel) -> None:
    """Refuse sensor positions farther from their centroid than SPREAD_RANGES x the sensor's range: no scan of one
    scene places its views so, but poses in millimetres do. The centroid, not the origin, so any world frame works."""
    t = poses[:, :3, 3]
    # Measured in units of the largest coordinate, then scaled back: squared, a pose at 1e300 m overflowed to inf
    # for every pose alike, and the first one was named.
    scale = float(np.abs(t).max()) or 1.0
    u = t / scale
    rel = np.linalg.norm(u - u.mean(axis=0), axis=1)
    i = int(np.argmax(rel))
    with np.errstate(over="ignore"):
        dist = rel * scale
    limit = SPREAD_RANGES * sensor.max_range_m
    if dist[i] > limit:
        raise DatasetError(f"{path}: pose {i} lies {dist[i]:.4g} m from the sensors' mean position, more than "
                           f"{SPREAD_RANGES} x the {sensor.name} sensor's range of {sensor.max_range_m:.2f} m; are the "
                           f"poses in millimetres? give them in metres")


def _temperature(rec: dict) -> tuple[bool, float | None]:
    """The on-chip temperature, distances[0].temperature: (given, value); value is None unless a finite number.
    Readers of temperature_c expect a number (the daemon stores one), so anything else is not copied there."""
    dist = rec.get("distances")
    if not (isinstance(dist, list) and dist and isinstance(dist[0], dict) and "temperature" in dist[0]):
        return False, None
    value = dist[0]["temperature"]
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
    return True, value if ok else None


def _temperature_notes(records: list[dict]) -> tuple[str, ...]:
    """One note naming how many measurements give a temperature that is not a number, and the first of them."""
    bad = [i for i, rec in enumerate(records) if _temperature(rec) == (True, None)]
    if not bad:
        return ()
    value = _clip(repr(records[bad[0]]["distances"][0]["temperature"]))
    many = f"{len(bad)} measurements give" if len(bad) > 1 else "1 measurement gives"
    return (f"{many} a distances[0].temperature that is not a number (first: measurement {bad[0]}, {value}); "
            f"stored without temperature_c (the original stays in its 'distances')",)


def _clip(text: str, width: int = 40) -> str:
    """A value quoted in a one-line message, cut to `width` characters."""
    return text if len(text) <= width else text[:width - 3] + "..."
