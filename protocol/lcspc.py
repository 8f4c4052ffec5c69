"""Reading the public LCSPCData format (CVPR 2024, MIT licence) and converting it into capture folders.

A file is a JSON list of measurements. Two kinds exist, told apart by the shape of `hists` (never by the file name):

- simulated: `{"hists": [1024 counts], "pose": 4x4}` -> sensor preset `lcspc-sim`, one zone;
- real (ams TMF8820 on a UR arm): `{"hists": 9 x 128, "reference_hist": 128, "pose": 4x4, "joint_angles": 6,
  "distances": [{on-chip depths mm, confidences, temperature C, tick, ...}], "time_captured": ...}`
  -> sensor preset `tmf8820`, nine zones in the sensor's channel order, the reference histogram kept.

Poses are sensor-to-world in metres with the sensor looking along +z, as in spadscan; a pose stored with the last row
[0, 0, 0, 0] (some real captures do) is read as the rigid transform it is when its 3x3 block is a rotation, with a
warning. Every key other than `hists`,
`pose` and `reference_hist` is kept verbatim in the measurement's metadata, plus `source_index` (the position in the
file) and `temperature_c` when the on-chip record gives one.
"""

from __future__ import annotations

import hashlib
import json
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
    reference = _references(path, records, sensor)
    meta = [_meta(path, i, r) for i, r in enumerate(records)]
    return LcspcData(path, kind, sensor, hists, poses, reference, meta, digest, _temperature_notes(records),
                     warnings)


def detect_kind(path, hists) -> tuple[str, SensorModel]:
    """('simulated' | 'real', sensor preset) from the shape of one measurement's `hists`."""
    shape = _shape(path, 0, "hists", hists)
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
def _read_bytes(path: Path, progress: Progress | None) -> tuple[bytes, str]:
    if not path.is_file():
        raise DatasetError(f"{path}: {'is a folder, not a' if path.is_dir() else 'no such'} LCSPCData JSON file")
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


def _shape(path, i: int, key: str, value) -> tuple[int, ...]:
    why = f"{path}: measurement {i} has a ragged or non-numeric {key!r}"
    try:
        a = np.asarray(value)
    except ValueError:  # nested lists of different lengths
        raise DatasetError(why) from None
    if a.dtype == object:  # mixed types, or integers too large for int64
        raise DatasetError(why)
    return a.shape


def _array(path, i: int, key: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """One measurement's array, reshaped to `shape` (a flat single-zone histogram gains its zone axis)."""
    got = _shape(path, i, key, value)
    a = np.asarray(value)
    if got != shape and not (got == shape[1:] and shape[0] == 1):
        want = shape[1:] if len(shape) == 2 and shape[0] == 1 else shape
        raise DatasetError(f"{path}: measurement {i} has {key} of shape {got}, expected {want}"
                           + (" (mixed kinds in one file?)" if key == "hists" else ""))
    if a.dtype.kind not in "iuf":
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
    zero_last = np.all(np.abs(poses[:, 3]) <= POSE_TOL, axis=1)
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
    value = repr(records[bad[0]]["distances"][0]["temperature"])
    value = value if len(value) <= 40 else value[:37] + "..."
    many = f"{len(bad)} measurements give" if len(bad) > 1 else "1 measurement gives"
    return (f"{many} a distances[0].temperature that is not a number (first: measurement {bad[0]}, {value}); "
            f"stored without temperature_c (the original stays in its 'distances')",)
