"""Reading capture folders: validated manifests and chunks, also while the scan is still being written."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .capture_format import (FORMAT, MANIFEST, SCHEDULE, STATES, VERSION, Chunk, NoPermission, check_hists,
                             check_poses, chunk_index, drawn_by_simulator, no_permission, one_line, read_json,
                             read_npy)
from .errors import CaptureError, SensorModelError
from .live_status import is_count
from .plausibility import check_counts, cycles_margin, first_photon_cycles
from .sensor_model import SensorModel

POSE_SPREAD_M = 1e-3
POSE_SPREAD_DEG = 0.5
"""How far the poses of the frames that share a pose_index may lie from their first frame's (metres, degrees of
rotation). Those frames are summed into one view at the first frame's pose (`CaptureData.by_pose`). A rig's readings
of one settled pose differ by microns (a daemon stores one arm reading for all of a pose's frames; a retaken pose
differs by the arm's repeatability, hundredths of a millimetre); another view lies centimetres and degrees away."""

NAMED_CHUNKS = 8
"""Chunks a capture's error or note names (the rest counted): the line stays one line with hundreds of them."""


@dataclass
class CaptureData:
    """A whole capture in memory. hists (N, zones, bins) uint32; poses (N, 4, 4) float64 metres;
    reference (N, bins) uint32 or None; meta: one dict per measurement (pose_index, frame, ...); notes: one-line
    warnings about what reading left out (reference histograms some chunks lack), carried by `check_counts`."""

    sensor: SensorModel
    hists: np.ndarray
    poses: np.ndarray
    reference: np.ndarray | None
    meta: list[dict]
    manifest: dict
    notes: tuple[str, ...] = ()

    @property
    def pose_indices(self) -> np.ndarray:
        return np.array([m["pose_index"] for m in self.meta], dtype=np.int64)

    def count_bounds(self) -> tuple:
        """(max_count, ignore_bins, cycles, margin): the bounds plausibility.survey_counts and .implausible test this
        capture's histograms against; the margin over the cycles is 1 for histograms this project's simulator drew
        (plausibility.cycles_margin)."""
        s = self.sensor
        return s.max_count, s.ignore_bins, first_photon_cycles(s), cycles_margin(drawn_by_simulator(self.manifest))

    def check_counts(self, where, warn: Callable[[str], None] | None = None) -> str | None:
        """Refuse (CaptureError naming `where`) a capture whose histograms no sensor could have produced (saturated,
        above the sensor's counter, all zero, all equal: see plausibility.py); when only some are, or some bins are
        clipped, return a one-line warning (also passed to `warn` as 'warning: ...'), else None. The line also
        carries the reading's `notes` (reference histograms left out): it is the capture's warning that a run
        prints and reports. For the readers that fit the counts (reconstruction, baselines); reading a capture does
        not check them."""
        max_count, ignore_bins, cycles, margin = self.count_bounds()
        note = check_counts(self.hists, max_count, ignore_bins, str(where), cycles, margin)
        for extra in self.notes:
            note = f"{note}; {extra}" if note else f"{where}: {extra}"
        if note and warn is not None:
            warn(f"warning: {note}")
        return note

    def by_pose(self) -> "PoseSums":
        """The frames of each pose summed into one view, views in pose-index order (what the reconstruction and
        the baselines' table search fit)."""
        _, first, group = np.unique(self.pose_indices, return_index=True, return_inverse=True)
        counts = np.zeros((len(first),) + self.hists.shape[1:], np.float64)
        np.add.at(counts, group, self.hists.astype(np.float64))
        return PoseSums(group=group, first=first, counts=counts,
                        frames=np.bincount(group, minlength=len(first)).astype(np.float64))


@dataclass
class PoseSums:
    """A capture's measurements grouped by pose. group (N,): the view of each measurement; first (V,): each view's
    first measurement (its pose is the view's); counts (V, zones, bins) float64: the frames' counts summed;
    frames (V,) float64: frames per view."""

    group: np.ndarray
    first: np.ndarray
    counts: np.ndarray
    frames: np.ndarray

    def in_any_frame(self, flags: np.ndarray) -> np.ndarray:
        """Per view, whether any of its frames holds `flags` (N, ...) bool, one per measurement: (V, ...) bool."""
        out = np.zeros((len(self.first),) + flags.shape[1:], bool)
        np.logical_or.at(out, self.group, flags)
        return out


def _check_version(version, where) -> None:
    """Refuse a manifest of a format version this reader does not know: a newer writer may have changed what the
    files mean, and reading them as version VERSION would be silently wrong. A manifest without one is version 1."""
    if version is None:
        return
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise CaptureError(f"{where}: version {version!r} must be a positive integer")
    if version > VERSION:
        raise CaptureError(f"{where}: capture format version {version} is newer than this spadscan reads "
                           f"(version {VERSION}); upgrade spadscan to read it")


MAX_INDEX = 2**53
"""The largest pose_index a reader takes (a plan of that many poses would never end; numpy's int64 holds it)."""


def _check_objects(m: dict, where) -> None:
    """`scene`, `rig` and `rig.sensor` are JSON objects where given (null reads as absent, as the worker reads it):
    the worker looks keys up in them, and a list or a string there ended a run in a traceback. `scene.real`, where
    given, is true or false: the string "false" is truthy, and a simulated capture was fitted as measured."""
    for key, value in (("scene", m.get("scene")), ("rig", m.get("rig"))):
        if value is not None and not isinstance(value, dict):
            raise CaptureError(f"{where}: {key} must be a JSON object, got {type(value).__name__}")
    sensor = (m.get("rig") or {}).get("sensor")
    if sensor is not None and not isinstance(sensor, dict):
        raise CaptureError(f"{where}: rig.sensor must be a JSON object, got {type(sensor).__name__}")
    scene_real(m.get("scene") or {}, where)


def scene_real(scene: dict, where) -> bool | None:
    """A manifest's `scene.real` (`scene`: its scene object): true or false where given, None where not; CaptureError
    naming `where` for anything else (the string "false" is truthy: a simulated capture was fitted as measured)."""
    if "real" not in scene:
        return None
    real = scene["real"]
    if not isinstance(real, bool):
        raise CaptureError(f"{where}: scene.real = {real!r} must be true or false")
    return real


def _check_pose_counts(m: dict, where) -> None:
    """`frames_per_pose` (an integer >= 1) and `planned_poses` (an integer >= 0), where given (null: not known): the
    frame numbers and pose indices are checked against them."""
    for key, least in (("frames_per_pose", 1), ("planned_poses", 0)):
        value = m.get(key)
        if value is not None and not (is_count(value) and value >= least):
            raise CaptureError(f"{where}: {key} {value!r} must be an integer >= {least}")


def _check_frame(record: dict, per_pose: int | None, where: str) -> None:
    """A measurement record's frame number, where it has one (another writer's record may not): an integer >= 0
    and, where the manifest gives frames_per_pose, below it (capture_format.md)."""
    frame = record.get("frame")
    if frame is None:
        return
    if not is_count(frame):
        raise CaptureError(f"{where} has frame {frame!r}, not an integer >= 0")
    if per_pose is not None and frame >= per_pose:
        raise CaptureError(f"{where} has frame {frame} of pose {record['pose_index']}, beyond the manifest's "
                           f"frames_per_pose {per_pose} (frames 0..{per_pose - 1})")


def _pose_spread(poses: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(shift in metres, turn in degrees) of each measurement's pose (N, 4, 4) from the first pose of its pose_index
    (indices (N,)): the pose its view is placed at when its frames are summed (CaptureData.by_pose)."""
    _, first, group = np.unique(indices, return_index=True, return_inverse=True)
    ref = poses[first[group.reshape(-1)]]
    shift = np.linalg.norm(poses[:, :3, 3] - ref[:, :3, 3], axis=1)
    cos = (np.einsum("nij,nij->n", poses[:, :3, :3], ref[:, :3, :3]) - 1) / 2  # trace(R_ref^T R) = 1 + 2 cos
    return shift, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _check_pose_spread(poses: np.ndarray, indices: np.ndarray, where) -> None:
    """Refuse frames of one pose_index whose poses lie more than POSE_SPREAD_M or POSE_SPREAD_DEG from the first:
    summed into one view at the first frame's pose, views taken elsewhere would be silently misplaced."""
    shift, turn = _pose_spread(poses, indices)
    apart = (shift > POSE_SPREAD_M) | (turn > POSE_SPREAD_DEG)
    if not apart.any():
        return
    pose = int(indices[apart][0])
    mine = indices == pose
    others = len(np.unique(indices[apart])) - 1
    more = f" (and {others} other pose(s))" if others else ""
    raise CaptureError(f"{where}: the frames of pose {pose}{more} were taken up to {1000 * shift[mine].max():.1f} mm "
                       f"and {turn[mine].max():.1f} degrees apart; the frames of one pose are summed into one view, "
                       f"so they must share it (within {1000 * POSE_SPREAD_M:g} mm and {POSE_SPREAD_DEG:g} degrees)")


def _named(names: list[str]) -> str:
    """`names` joined, the first NAMED_CHUNKS of them named and the rest counted."""
    rest = len(names) - NAMED_CHUNKS
    return ", ".join(names[:NAMED_CHUNKS]) + (f" and {rest} more" if rest > 0 else "")


def _reference_note(chunks: list[Chunk]) -> str | None:
    """Why no reference histogram is used, when some chunks hold reference.npy and others lack it (the capture's
    references are kept for every measurement or for none), else None."""
    lacking = [c.name for c in chunks if c.reference is None]
    if not lacking or len(lacking) == len(chunks):
        return None
    return (f"reference.npy is missing from {len(lacking)} of {len(chunks)} chunks ({_named(lacking)}): no "
            f"reference histogram is used, not even the other chunks' (a measured capture's pulse is then the "
            f"sensor model's)")


def _is_there(path: Path) -> bool:
    """Whether the file at `path` exists. A lookup that fails (a disk error, a folder this user may not search) is a
    one-line CaptureError (NoPermission for the latter), as for a chunk file that cannot be read, never a bare
    OSError: Path.exists raises every error but those that say the file is not there."""
    try:
        return path.exists()
    except PermissionError:
        raise no_permission(path) from None
    except OSError as exc:
        raise CaptureError(f"{path}: cannot be read ({one_line(exc)})") from None


@dataclass
class ChunkRead:
    """One published chunk as read: the chunk when whole, else why it cannot be read. error is a NoPermission for a
    chunk this user may not read (forbidden: its owner or mode, its content may be intact), any other CaptureError
    for a damaged one (torn or zeroed files after a power cut, a disk error)."""

    name: str
    chunk: Chunk | None = None
    error: CaptureError | None = None

    @property
    def forbidden(self) -> bool:
        return isinstance(self.error, NoPermission)

    @property
    def damaged(self) -> bool:
        return self.error is not None and not self.forbidden


class CaptureReader:
    """Reads one capture folder (the folder that holds `scan.json`). Every problem is a one-line CaptureError."""

    def __init__(self, path):
        self.path = Path(path)
        if not self.path.is_dir():
            raise CaptureError(f"{self.path}: " + ("a file, not a capture folder" if self.path.exists() else
                                                    "no such capture folder"))
        self.manifest = self._read_manifest()
        where = self.path / MANIFEST
        try:
            self.sensor = SensorModel.from_dict(self.manifest["sensor"])
        except SensorModelError as exc:
            raise CaptureError(f"{where}: {exc}") from None
        except (TypeError, ValueError) as exc:  # a field of the wrong JSON type (a string for a number, ...)
            raise CaptureError(f"{where}: malformed sensor model ({one_line(exc)})") from None
        try:
            hand_eye = np.asarray(self.manifest.get("hand_eye", np.eye(4).tolist()), dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise CaptureError(f"{where}: hand_eye is not a 4x4 matrix ({one_line(exc)})") from None
        self.hand_eye = check_poses(hand_eye[None], f"{where} hand_eye")[0]

    def _read_manifest(self) -> dict:
        where = self.path / MANIFEST
        m = read_json(where)
        if m.get("format") != FORMAT:
            raise CaptureError(f"{where}: not a spadscan capture (format {m.get('format')!r})")
        _check_version(m.get("version"), where)
        for key in ("state", "sensor", "chunk_size"):
            if key not in m:
                raise CaptureError(f"{where}: lacks {key!r}")
        size = m["chunk_size"]
        if not (isinstance(size, int) and not isinstance(size, bool) and size >= 1):
            raise CaptureError(f"{where}: chunk_size {size!r} must be a positive integer")
        if m["state"] not in STATES:
            raise CaptureError(f"{where}: state {m['state']!r} is not one of {STATES}")
        _check_objects(m, where)
        _check_pose_counts(m, where)
        return m

    def refresh(self) -> str:
        """Re-read the manifest; returns the scan state."""
        self.manifest = self._read_manifest()
        return self.manifest["state"]

    @property
    def state(self) -> str:
        return self.manifest["state"]

    @property
    def scan_id(self) -> str:
        return self.manifest.get("scan_id", self.path.name)

    def planned_poses(self) -> np.ndarray | None:
        """Planned sensor poses (P, 4, 4), when the scan stored its schedule."""
        p = self.path / SCHEDULE
        return check_poses(read_npy(p), str(p)) if p.exists() else None

    def chunk_names(self) -> list[str]:
        """Published chunks in order (temporary folders of a chunk being written are never listed)."""
        # os.scandir: an entry knows whether it is a folder without a stat each (10,000 chunks: ms, not 0.1 s).
        with os.scandir(self.path) as entries:
            names = [e.name for e in entries if chunk_index(e.name) is not None and e.is_dir()]
        return sorted(names)

    def read_chunk(self, name: str) -> Chunk:
        d = self.path / name
        s = self.sensor
        hists = check_hists(read_npy(d / "hists.npy"), s.n_zones, s.n_bins, str(d / "hists.npy"))
        n = hists.shape[0]
        poses = read_npy(d / "poses.npy")
        if poses.dtype != np.float64:
            raise CaptureError(f"{d / 'poses.npy'}: poses have dtype {poses.dtype}, expected float64")
        poses = check_poses(poses, str(d / "poses.npy"))
        if poses.shape[0] != n:
            raise CaptureError(f"{d / 'poses.npy'}: {poses.shape[0]} poses for {n} histograms")
        ref = None
        if _is_there(d / "reference.npy"):
            ref = read_npy(d / "reference.npy")
            if ref.shape != (n, s.n_bins) or ref.dtype != np.uint32:
                raise CaptureError(f"{d / 'reference.npy'}: shape {ref.shape} {ref.dtype}, expected "
                                   f"({n}, {s.n_bins}) uint32")
        meta = read_json(d / "meta.json").get("measurements")
        if not isinstance(meta, list) or len(meta) != n:
            raise CaptureError(f"{d / 'meta.json'}: expected {n} measurement records")
        for i, m in enumerate(meta):
            index = m.get("pose_index") if isinstance(m, dict) else None
            if not is_count(index):
                raise CaptureError(f"{d / 'meta.json'}: measurement {i} lacks a pose_index >= 0")
            if index > MAX_INDEX:
                raise CaptureError(f"{d / 'meta.json'}: measurement {i} has pose_index {index}, over {MAX_INDEX:,}")
        return Chunk(name, hists, poses, ref, meta)

    def try_read_chunk(self, name: str) -> ChunkRead:
        """Chunk `name` read, or why it cannot be: whole, damaged or forbidden (ChunkRead). The one place that tells
        them apart, for loading a capture and for the daemon's advice on one it could not take over."""
        try:
            return ChunkRead(name, chunk=self.read_chunk(name))
        except CaptureError as exc:
            return ChunkRead(name, error=exc)

    def _readable_chunks(self) -> list[Chunk]:
        """Every published chunk, read. One that cannot be read (torn or zeroed files after a power cut) raises its
        own error, to which the way out is added: the other chunks are read first so that it can say how many are
        whole, since setting the damaged ones aside leaves their views to use. A chunk this user may not read is not
        damaged (its content may be intact) and gets no such advice."""
        chunks, damaged, first = [], [], None
        for name in self.chunk_names():
            read = self.try_read_chunk(name)
            if read.forbidden:
                raise read.error
            if read.damaged:
                damaged.append(name)
                first = first or read.error
            else:
                chunks.append(read.chunk)
        if first is None:
            return chunks
        if not chunks:
            raise CaptureError(f"{first}; none of its {len(damaged)} chunks can be read") from None
        them = "it" if len(damaged) == 1 else "them"
        raise CaptureError(f"{first}; {len(damaged)} of {len(damaged) + len(chunks)} chunks cannot be read "
                           f"({_named(damaged)}): moving {them} out of {self.path} leaves the views of the other "
                           f"{len(chunks)} to use") from None

    def follow(self, poll_s: float = 0.5, timeout_s: float | None = None) -> Iterator[Chunk]:
        """Yield chunks as they are published until the scan is no longer running (and all chunks are read).

        Raises CaptureError if `timeout_s` passes with the scan still running and nothing new.
        """
        seen: set[str] = set()
        last_new = time.monotonic()
        while True:
            state = self.refresh()
            new = [n for n in self.chunk_names() if n not in seen]
            for name in new:
                seen.add(name)
                yield self.read_chunk(name)
            if new:
                last_new = time.monotonic()
            elif state != "running":
                return
            elif timeout_s is not None and time.monotonic() - last_new > timeout_s:
                raise CaptureError(f"{self.path}: no new chunk for {timeout_s:.0f} s while the scan is running")
            else:
                time.sleep(poll_s)

    def load(self) -> CaptureData:
        """Every published measurement, concatenated in order. An empty capture is an error, and so is one with a
        chunk that cannot be read (`_readable_chunks`), a bad schedule.npy or a pose_index beyond it
        (`_check_planned`), a frame number beyond frames_per_pose (`_check_frames`), and frames of one pose_index
        taken at different poses (`_check_pose_spread`).
        Reference histograms are kept only when every chunk holds them (else a note says so)."""
        chunks = self._readable_chunks()
        if not chunks:
            raise CaptureError(f"{self.path}: holds no published measurements")
        self._check_planned(chunks)
        self._check_frames(chunks)
        poses = np.concatenate([c.poses for c in chunks])
        _check_pose_spread(poses, np.concatenate([c.pose_indices for c in chunks]), self.path)
        refs = [c.reference for c in chunks]
        reference = np.concatenate(refs) if all(r is not None for r in refs) else None
        note = _reference_note(chunks)
        return CaptureData(
            sensor=self.sensor,
            hists=np.concatenate([c.hists for c in chunks]),
            poses=poses,
            reference=reference,
            meta=[m for c in chunks for m in c.meta],
            manifest=self.manifest,
            notes=(note,) if note else (),
        )

    def _check_frames(self, chunks: list[Chunk]) -> None:
        """Every record's frame number, where it has one, is an integer >= 0 below the manifest's frames_per_pose
        (where given). Checked on the whole capture, not as a chunk is read: a chunk with such a record is not
        damaged, and moving it out is no remedy."""
        per_pose = self.manifest.get("frames_per_pose")
        for c in chunks:
            for i, record in enumerate(c.meta):
                _check_frame(record, per_pose, f"{self.path / c.name / 'meta.json'}: measurement {i}")

    def _check_planned(self, chunks: list[Chunk]) -> None:
        """schedule.npy, where there is one, holds rigid finite poses (`planned_poses`), and every measurement's
        pose_index names one of the planned poses where their number is known: the schedule's rows, else the
        manifest's planned_poses. One line naming the file otherwise."""
        schedule = self.planned_poses()
        planned = len(schedule) if schedule is not None else self.manifest.get("planned_poses")
        if planned is None:
            return
        of = str(self.path / SCHEDULE) if schedule is not None else f"{self.path / MANIFEST} (planned_poses)"
        for c in chunks:
            beyond = np.flatnonzero(c.pose_indices >= planned)
            if beyond.size:
                i = int(beyond[0])
                raise CaptureError(f"{self.path / c.name / 'meta.json'}: measurement {i} has pose_index "
                                   f"{c.meta[i]['pose_index']}, beyond the {planned} planned poses of {of}")


def check_capture_counts(capture, warn: Callable[[str], None] | None = None) -> str | None:
    """Read the capture folder `capture` and check its counts (CaptureData.check_counts): a CaptureError for
    histograms no sensor could have produced, a warning (returned, and passed to `warn`) when only some are."""
    return CaptureReader(capture).load().check_counts(capture, warn)
