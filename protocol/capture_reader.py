"""Reading capture folders: validated manifests and chunks, also while the scan is still being written."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .capture_format import (FORMAT, MANIFEST, SCHEDULE, STATES, VERSION, Chunk, NoPermission, check_hists,
                             check_poses, chunk_index, no_permission, one_line, read_json, read_npy)
from .errors import CaptureError, SensorModelError
from .plausibility import check_counts, first_photon_cycles
from .sensor_model import SensorModel


@dataclass
class CaptureData:
    """A whole capture in memory. hists (N, zones, bins) uint32; poses (N, 4, 4) float64 metres;
    reference (N, bins) uint32 or None; meta: one dict per measurement (pose_index, frame, ...)."""

    sensor: SensorModel
    hists: np.ndarray
    poses: np.ndarray
    reference: np.ndarray | None
    meta: list[dict]
    manifest: dict

    @property
    def pose_indices(self) -> np.ndarray:
        return np.array([m["pose_index"] for m in self.meta], dtype=np.int64)

    def check_counts(self, where, warn: Callable[[str], None] | None = None) -> str | None:
        """Refuse (CaptureError naming `where`) a capture whose histograms no sensor could have produced (saturated,
        above the sensor's counter, all zero, all equal: see plausibility.py); when only some are, or some bins are
        clipped, return a one-line warning (also passed to `warn` as 'warning: ...'), else None. For the readers
        that fit the counts (reconstruction, baselines); reading a capture does not check them."""
        note = check_counts(self.hists, self.sensor.max_count, self.sensor.ignore_bins, str(where),
                            first_photon_cycles(self.sensor))
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


NAMED_CHUNKS = 8
"""Damaged chunks a capture's error names (the rest counted): the line stays one line with hundreds of them."""


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
        names = [p.name for p in self.path.iterdir() if chunk_index(p.name) is not None and p.is_dir()]
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
            if not isinstance(index, int) or isinstance(index, bool) or index < 0:
                raise CaptureError(f"{d / 'meta.json'}: measurement {i} lacks a pose_index >= 0")
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
        named = ", ".join(damaged[:NAMED_CHUNKS]) + (f" and {len(damaged) - NAMED_CHUNKS} more"
                                                      if len(damaged) > NAMED_CHUNKS else "")
        raise CaptureError(f"{first}; {len(damaged)} of {len(damaged) + len(chunks)} chunks cannot be read "
                           f"({named}): moving {them} out of {self.path} leaves the views of the other "
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
        chunk that cannot be read (`_readable_chunks`)."""
        chunks = self._readable_chunks()
        if not chunks:
            raise CaptureError(f"{self.path}: holds no published measurements")
        refs = [c.reference for c in chunks]
        reference = np.concatenate(refs) if all(r is not None for r in refs) else None
        return CaptureData(
            sensor=self.sensor,
            hists=np.concatenate([c.hists for c in chunks]),
            poses=np.concatenate([c.poses for c in chunks]),
            reference=reference,
            meta=[m for c in chunks for m in c.meta],
            manifest=self.manifest,
        )


def check_capture_counts(capture, warn: Callable[[str], None] | None = None) -> str | None:
    """Read the capture folder `capture` and check its counts (CaptureData.check_counts): a CaptureError for
    histograms no sensor could have produced, a warning (returned, and passed to `warn`) when only some are."""
    return CaptureReader(capture).load().check_counts(capture, warn)
