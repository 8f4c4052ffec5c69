"""Writing capture folders: chunks published by one atomic rename, a manifest that records the scan's state.

A chunk is written into a hidden temporary folder, every file fsynced, then renamed to `chunk-NNNNNN` and the parent
folder fsynced: a reader sees a whole chunk or none, and a crash loses only what was not yet flushed. `resume` reopens
a scan, removes half-written temporary folders and continues after the last published chunk. The measurements it
lacks before its first unpublished pose (a damaged chunk the operator moved out) are listed in `retakes`, each with
the free chunk numbers that put it back in pose order; until they are published again the capture cannot be marked
complete. A writer keeps a `ChunkBook` of the chunks it read or published; reopened with it (`resume(path,
known=book)`), it reads again only the chunks whose files changed since (a pause's resume does not read a
10,000-pose capture whole), and still notices every chunk moved out, renamed, added or altered.

A chunk's files are written and fsynced side by side, one thread each, and the publish waits for all of them: the
same fsyncs as one after the other, but a journaling filesystem (ext4's jbd2) commits them together, so a durable
publish costs about two journal commits (the files, then the rename) instead of one per file.

A writer holds an exclusive flock on the capture folder itself (its writer lock) for as long as it is open: another
process's `create` or `resume` of the same capture is refused while it is held (a second daemon on the same captures
root would otherwise drive a second arm through the same poses and delete this writer's half-written chunks). The
folder's inode stays for as long as the capture exists (scan.json, replaced by rename, would not do), and locking it
adds no file to the capture. flock belongs to an open file description, so the writers of one capture within one
process share one descriptor (the daemon reopens its own scans); the last of them closed (`close`, or dropped)
releases it, and the kernel releases it when the process dies.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import threading
import time
import weakref
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path

import numpy as np

try:
    import resource
except ImportError:  # not on Windows, which has no per-process file-size limit
    resource = None
try:
    import fcntl
except ImportError:  # not on Windows: no flock there, and no writer lock
    fcntl = None

from .capture_format import (CHUNK_PREFIX, FORMAT, MANIFEST, SCHEDULE, STATES, TMP_PREFIX, VERSION, Measurement,
                             check_json, check_poses, chunk_index, chunk_name, fold, fsync_dir, one_line, read_json,
                             save_npy_durable, strict_json, to_counts, write_durable, write_json_atomic)
from .capture_reader import CaptureReader
from .disk_full import is_short_write
from .errors import CaptureError
from .iso_time import utc_now
from .sensor_model import SensorModel

PAUSE = "pause"
"""scan.json's `paused.kind` when someone or something paused the scan: the operator (`ctl pause`), a fault."""
INTERRUPTED = "interrupted"
"""scan.json's `paused.kind` when no one paused the scan: its daemon stopped while it ran, and a later one took it
over and waits (for `ctl resume`, or for what stands in the way: a full disk, a changed rig). The daemon after that
takes it for no pause: with auto_resume it goes on by itself."""
PAUSE_KINDS = (PAUSE, INTERRUPTED)
_HELD: dict[tuple[int, int], list[int]] = {}
"""The writer locks this process holds: (st_dev, st_ino) of the capture folder -> [descriptor, writers open on it]."""
_HELD_GUARD = threading.Lock()
_NO_FLOCK = (errno.EBADF, errno.EINVAL, errno.ENOLCK, errno.EOPNOTSUPP)
"""flock's errors where the filesystem cannot lock a folder (some network filesystems): the writer goes on unlocked
there, as it did before it locked at all, rather than refuse every capture on such a disk."""


def _open_folder(path: Path) -> int:
    return os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)


def writer_lock_held(path) -> bool:
    """Whether another process holds the writer lock of the capture folder `path` (a writer of it is open there).
    False where the folder cannot be opened or locked, or this process holds it."""
    if fcntl is None:
        return False
    try:
        fd = _open_folder(Path(path))
    except OSError:
        return False
    try:
        st = os.fstat(fd)
        with _HELD_GUARD:
            if (st.st_dev, st.st_ino) in _HELD:
                return False
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        except OSError:
            return False
        return False
    finally:
        os.close(fd)  # (drops the shared lock taken to look)


def _writing_elsewhere(path: Path) -> str:
    """A refusal to open the capture at `path` whose writer lock another process holds, on one line."""
    return (f"{path}: another process is writing this capture (it holds the folder's writer lock); stop that process "
            f"(another daemon on the same captures root?) before opening it here")


def _flock_retrying(fd: int, tries: int = 10, wait_s: float = 0.02) -> None:
    """An exclusive flock on `fd`, tried `tries` times `wait_s` apart: another process's `writer_lock_held` holds a
    shared lock for a moment only, and must not make a writer's open fail. The last refusal is raised."""
    for k in range(tries):
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if k == tries - 1:
                raise
            time.sleep(wait_s)


def _take_writer_lock(path: Path) -> tuple[int, int] | None:
    """Hold the writer lock of the capture folder `path` (an exclusive flock on the folder itself: its inode stays
    for as long as the capture exists, whatever is renamed in it) for one more writer of this process; its key (for
    `_release_writer_lock`), None where nothing is locked (no flock, or a filesystem that cannot lock a folder).
    CaptureError when another process holds it; an OSError naming the folder when it cannot be opened."""
    if fcntl is None:
        return None
    try:
        fd = _open_folder(path)
    except OSError as exc:
        raise _named(exc, path) from None
    try:
        st = os.fstat(fd)
    except OSError as exc:
        os.close(fd)
        raise _named(exc, path) from None
    key = (st.st_dev, st.st_ino)
    with _HELD_GUARD:
        held = _HELD.get(key)
        if held is not None:  # another writer of this process has it: a second flock here would refuse it
            held[1] += 1
            os.close(fd)
            return key
        try:
            _flock_retrying(fd)
        except OSError as exc:
            os.close(fd)
            if isinstance(exc, BlockingIOError):
                raise CaptureError(_writing_elsewhere(path)) from None
            if exc.errno in _NO_FLOCK:
                return None
            raise _named(exc, path) from None
        _HELD[key] = [fd, 1]
    return key


def _release_writer_lock(key: tuple[int, int] | None) -> None:
    """One writer of this process less on the lock `key`; the last one closes its descriptor, which drops the flock."""
    if key is None:
        return
    with _HELD_GUARD:
        held = _HELD.get(key)
        if held is None:
            return
        held[1] -= 1
        if held[1] > 0:
            return
        del _HELD[key]
    with contextlib.suppress(OSError):
        os.close(held[0])


def _named(exc: OSError, path) -> OSError:
    """The same error, naming the file it happened to. A write into an open file raises without a filename, and
    numpy's short write ("8192 requested and 3040 written") without an errno either; a user needs the path, and the
    CLI needs the errno to say what stopped the write (`_short_write`)."""
    if exc.filename is not None:
        return exc
    if is_short_write(exc):
        named = _short_write(path)
    else:
        named = OSError(exc.errno, exc.strerror or str(exc), str(path)) if exc.errno is not None else exc
    return named


def file_size_limit() -> int | None:
    """The largest file (bytes) this process may write (RLIMIT_FSIZE, `ulimit -f`); None when unlimited (or where
    there is no such limit)."""
    if resource is None:
        return None
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return None if soft == resource.RLIM_INFINITY else int(soft)


def held_frames(records) -> list[tuple[int, int | None]]:
    """(pose_index, frame number or None) of each measurement record of a chunk, as `plan_retakes` reads them."""
    return [(int(m["pose_index"]), frame_number(m)) for m in records]


def _short_write(path) -> OSError:
    """What numpy's short write of `path` stands for: EFBIG when the file reached this process's file-size limit
    (`ulimit -f`, RLIMIT_FSIZE: the kernel writes up to it, then refuses; a full disk's advice, make room, would not
    help), else ENOSPC (the disk filled up under it)."""
    limit = file_size_limit()
    try:
        size = os.stat(path).st_size
    except OSError:
        size = None
    limited = limit is not None and size is not None and size >= limit
    code = errno.EFBIG if limited else errno.ENOSPC
    return OSError(code, os.strerror(code), str(path))


def _write(fn, path, *args) -> None:
    """fn(path, *args); an OSError names `path`."""
    try:
        fn(path, *args)
    except OSError as exc:
        named = _named(exc, path)
        if named is exc:
            raise
        raise named from exc


def _together(calls: list) -> None:
    """Run calls [(fn, path, *args)] side by side (the first in this thread) and wait for all of them; then raise
    the first error, if any. Waiting for all means no file is still being written when the caller moves on."""
    errors: list[BaseException | None] = [None] * len(calls)

    def run(k: int) -> None:
        try:
            _write(*calls[k])
        except BaseException as exc:  # handed to the caller below
            errors[k] = exc

    threads = [threading.Thread(target=run, args=(k,), name="capture-fsync") for k in range(1, len(calls))]
    for t in threads:
        t.start()
    try:
        run(0)
    finally:
        for t in threads:
            t.join()
    for exc in errors:
        if exc is not None:
            raise exc


def frame_number(record: dict) -> int | None:
    """A measurement record's frame number; None when it has none (another writer's capture: `plan_retakes` takes
    its pose as whole)."""
    frame = record.get("frame")
    return frame if isinstance(frame, int) and not isinstance(frame, bool) else None


def _drop_temporary(path: Path) -> None:
    """Remove the hidden temporary folders and files of chunks and manifests that were never published."""
    for p in path.iterdir():
        if p.name.startswith(TMP_PREFIX):
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)


def _undo_create(path: Path, made: bool) -> None:
    """Best effort (the error that stopped `create` is the one to report): remove the files a failed `create` wrote,
    and the folder when it made it."""
    with contextlib.suppress(OSError):
        for name in (SCHEDULE, MANIFEST):
            (path / name).unlink(missing_ok=True)
        _drop_temporary(path)  # the manifest's temporary file
        if made:
            path.rmdir()  # not rmtree: whatever someone else put there meanwhile stays


def _occupied(path: Path) -> str:
    """Why `create` refuses a folder with a manifest, and what to do. Only simulations and imports get here (the
    daemon never reuses a scan name, and resumes its own scans with `resume`), and they cannot continue a capture:
    an unfinished one must be deleted or left alone."""
    try:
        manifest = read_json(path / MANIFEST)
        state, reason = manifest.get("state"), manifest.get("reason")
    except CaptureError:  # a manifest too damaged to read still marks the folder as taken
        state, reason = None, None
    if state == "complete":
        return f"{path}: already holds a capture (complete); choose another folder"
    why = "unreadable scan.json"
    if state is not None:
        why = f"state {state!r}" + (f": {fold(reason)}" if reason else "")  # another writer's reason may span lines
    return f"{path}: already holds a capture that was not finished ({why}); delete the folder or choose another"


CHUNK_FILES = ("hists.npy", "poses.npy", "meta.json", "reference.npy")
"""Every file a chunk's reading looks at (`CaptureReader.read_chunk`)."""


def chunk_stamp(folder) -> tuple | None:
    """What the files of the chunk `folder` look like to the filesystem: (name, inode, size, mtime_ns, ctime_ns) of
    each of CHUNK_FILES (only the name where it is absent). A file replaced, rewritten, truncated, added or removed
    changes it (a rewrite changes ctime, which no tool sets back); None when a file cannot be looked up."""
    out, folder = [], os.fspath(folder)
    for name in CHUNK_FILES:
        try:
            st = os.stat(os.path.join(folder, name))  # (not pathlib: its objects cost more than the stat)
        except FileNotFoundError:
            out.append((name,))
            continue
        except OSError:
            return None
        out.append((name, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns))
    return tuple(out)


@dataclass(frozen=True)
class ChunkRecord:
    """One published chunk as a writer knows it: `stamp` (`chunk_stamp`) when it was read whole or published, and
    `held`, the (pose_index, frame) of its measurements (`held_frames`)."""

    stamp: tuple
    held: tuple[tuple[int, int | None], ...]


@dataclass
class ChunkBook:
    """The published chunks of the capture at `path` that a writer read whole or published, by folder name, checked
    against a sensor of `shape` (zones, bins). Handed to `CaptureWriter.resume` (`known`), it spares reading again a
    chunk whose stamp is unchanged: a published chunk never changes, and what was checked in it still holds. Kept
    in memory only (a daemon's own scans); a writer updates it as it publishes."""

    path: Path
    shape: tuple[int, int]
    chunks: dict[str, ChunkRecord] = field(default_factory=dict)

    def record(self, name: str, held) -> None:
        """Note chunk `name` with measurements `held` [(pose_index, frame)], as its files stand now."""
        stamp = chunk_stamp(os.path.join(self.path, name))
        if stamp is not None:  # (one that cannot be looked up is read whole next time)
            self.chunks[name] = ChunkRecord(stamp, tuple(held))

    def unchanged(self, name: str, stamp: tuple | None) -> ChunkRecord | None:
        """The record of chunk `name` when its files still have `stamp`, else None (read it whole)."""
        record = self.chunks.get(name)
        return record if record is not None and stamp is not None and record.stamp == stamp else None


@dataclass(frozen=True)
class Retake:
    """Measurements a resumed capture lacks before its first unpublished pose (a damaged chunk moved out of it): pose
    `pose`'s frames `frames`, taken again and published under the chunk numbers `chunks`: free numbers between the
    chunks of the poses before and after it, so that the chunks in name order still hold the poses in order (None:
    the next numbers after the last chunk, for the last pose's frames)."""

    pose: int
    frames: tuple[int, ...]
    chunks: tuple[int, ...] | None


def frames_per_pose(manifest: dict) -> int:
    """A manifest's frames_per_pose, 1 where it gives none or no whole number of at least 1."""
    frames = manifest.get("frames_per_pose", 1)
    return frames if isinstance(frames, int) and not isinstance(frames, bool) and frames >= 1 else 1


def plan_retakes(chunks: list[tuple[int, list[tuple[int, int | None]]]], frames_per_pose: int, chunk_size: int,
                 where) -> list[Retake]:
    """The Retakes of a capture whose chunks are `chunks` [(number, [(pose_index, frame), ...])]: every frame
    0 .. frames_per_pose - 1 of every pose up to the last published one that is not there. A pose with a record
    lacking a frame number is taken as whole (another writer's capture). CaptureError when a pose's frames cannot be
    put back in order (no chunk number free between its neighbours': the chunks were renumbered)."""
    held: dict[int, set] = {}
    spans = []  # (number, lowest pose, highest pose) of each chunk
    for number, pairs in chunks:
        for pose, frame in pairs:
            held.setdefault(pose, set()).add(frame)
        if pairs:
            poses = [pose for pose, _ in pairs]
            spans.append((number, min(poses), max(poses)))
    used = {number for number, _ in chunks}
    out, given = [], -1  # given: the highest chunk number handed to a retake so far (retakes stay in pose order)
    for pose in range(max(held) + 1 if held else 0):
        have = held.get(pose, set())
        missing = () if None in have else tuple(f for f in range(frames_per_pose) if f not in have)
        if not missing:
            continue
        after = min((n for n, _, high in spans if high > pose), default=None)
        if after is None:  # the last pose: its frames go after every chunk
            out.append(Retake(pose, missing, None))
            continue
        before = max((n for n, low, _ in spans if low < pose), default=-1)
        need = -(-len(missing) // chunk_size)
        free = tuple(islice((n for n in range(max(before, given) + 1, after) if n not in used), need))
        if len(free) < need:
            low = max(before, given)
            raise CaptureError(f"{where}: pose {pose} lacks frame(s) {', '.join(map(str, missing))} and cannot take "
                               f"them again in order: no chunk number is free "
                               f"{f'between {chunk_name(low)} and' if low >= 0 else 'before'} {chunk_name(after)} "
                               f"(a capture lists its poses in chunk order; were its chunks renamed?)")
        given = free[-1]
        out.append(Retake(pose, missing, free))
    return out


@dataclass(frozen=True)
class Stock:
    """What a capture's published chunks hold, as every reader of its progress counts it (`count_stock`): the
    measurements published, the poses they are of, and the Retakes owed before the first unpublished pose."""

    published: int
    poses: frozenset[int]
    retakes: tuple[Retake, ...]

    @property
    def next_pose(self) -> int:
        """The first pose not published (poses are published in order): where the scan goes on."""
        return max(self.poses) + 1 if self.poses else 0


def count_stock(chunks: list[tuple[int, list[tuple[int, int | None]]]], manifest: dict, where) -> Stock:
    """The Stock of a capture whose manifest is `manifest` and whose published chunks are `chunks` [(number,
    [(pose_index, frame), ...])]: one count for a writer's reopening (`CaptureWriter.resume`), its check for chunks
    gone (`take_stock`) and a daemon's counts without a writer, so that they never disagree. CaptureError as
    `plan_retakes`."""
    retakes = plan_retakes(chunks, frames_per_pose(manifest), int(manifest["chunk_size"]), where)
    return Stock(sum(len(pairs) for _, pairs in chunks), frozenset(pose for _, pairs in chunks for pose, _ in pairs),
                 tuple(retakes))


def mark_paused(path, reason: str, kind: str = PAUSE) -> None:
    """Record in the manifest of the capture at `path` that its scan is paused, why, and what kind of pause it is
    (`paused`: {"reason", "since_utc", "kind"}: one of PAUSE_KINDS; the state stays 'running'): a daemon restarted
    meanwhile takes it over paused, and a reader can say so. Only the manifest is read and written (no chunk: a
    writer reopened for this would read them all), so the scan's writer, if one is open, must not be writing
    meanwhile; its next recorded state (`set_state`: the scan goes on, or ends) clears the record, and nothing else
    does."""
    if kind not in PAUSE_KINDS:
        raise CaptureError(f"pause kind {kind!r} is not one of {PAUSE_KINDS}")
    manifest_path = Path(path) / MANIFEST
    manifest = read_json(manifest_path)
    reason = fold(reason)
    # The same pause recorded again (the daemon stopped or restarted while it held) keeps the time it began: going
    # on removes the record, so one that is there is this pause's.
    held = manifest.get("paused")
    since = held.get("since_utc") if isinstance(held, dict) else None
    since = since if isinstance(since, str) else utc_now()
    manifest.update(state="running", reason=reason, paused={"reason": reason, "since_utc": since, "kind": kind},
                    updated_utc=utc_now())
    _write(write_json_atomic, manifest_path, manifest)


def mark_aborted(path, reason: str) -> None:
    """Record in the manifest of the capture at `path` that its scan is aborted, and why; a pause's record goes. Only
    the manifest is read and written: no chunk is read (a capture with a damaged chunk can be ended too) and nothing
    is published, so the write needs room for the manifest alone. The scan's writer, if one is open, must not be
    writing meanwhile: CaptureError when another process holds the capture's writer lock."""
    if writer_lock_held(path):
        raise CaptureError(_writing_elsewhere(Path(path)))
    manifest_path = Path(path) / MANIFEST
    manifest = read_json(manifest_path)
    manifest.pop("paused", None)
    manifest.update(state="aborted", reason=fold(reason), updated_utc=utc_now())
    _write(write_json_atomic, manifest_path, manifest)


def drop_temporary(path) -> None:
    """Remove the hidden temporary chunk folders and manifest files no writer finished in the capture at `path` (a
    full disk's half-written chunk: freeing its room may let the manifest be written). No writer may be writing the
    capture meanwhile: nothing is removed while another process holds its writer lock (they are that writer's)."""
    if not writer_lock_held(path):
        _drop_temporary(Path(path))


class CaptureWriter:
    """Appends measurements to one capture folder. Not thread-safe: one writer per scan.

    Use `create` for a new scan and `resume` to continue one; `append` buffers, `flush` publishes the buffer as a
    chunk (the daemon flushes at the end of every pose so that a finished pose is durable), `finish` marks the
    state. As a context manager it flushes on exit and leaves the state 'running' if the block raised.
    """

    def __init__(self, path: Path, manifest: dict, sensor: SensorModel, next_chunk: int, published: int,
                 pose_indices: set[int], retakes: list[Retake] | None = None, book: ChunkBook | None = None,
                 lock: tuple[int, int] | None = None):
        self.path = Path(path)
        # The writer lock (`_take_writer_lock`) is released by `close`, or when the writer is dropped unclosed.
        self._release = weakref.finalize(self, _release_writer_lock, lock)
        self.book = book if book is not None else ChunkBook(self.path, (sensor.n_zones, sensor.n_bins))
        """The chunks this writer read whole or published (`resume(path, known=...)` of a later writer)."""
        self.manifest = manifest
        self.sensor = sensor
        self._next_chunk = next_chunk
        self._buffer: list[Measurement] = []
        self.n_published = published
        self.published_pose_indices = pose_indices
        self.retakes: list[Retake] = list(retakes or [])
        """What a resumed capture lacks before its first unpublished pose, in pose order (`publish_retake`)."""

    def close(self) -> None:
        """Release this writer's hold on the capture's writer lock; the buffer is not flushed. Once
        every writer of the capture in this process is closed, another process may open it."""
        self._release()

    # ---- opening -------------------------------------------------------------------------------------------------
    @classmethod
    def create(cls, path, sensor: SensorModel, *, scan_id: str | None = None, rig: dict | None = None,
               hand_eye: np.ndarray | None = None, schedule: dict | None = None,
               planned_poses: np.ndarray | None = None, chunk_size: int = 64, scene: dict | None = None,
               frames_per_pose: int = 1) -> "CaptureWriter":
        """Start a new scan folder. Refuses a folder that already holds a capture (use `resume`)."""
        path = Path(path)
        if path.exists() and not path.is_dir():
            raise CaptureError(f"{path}: exists and is not a folder")
        if (path / MANIFEST).exists():
            raise CaptureError(_occupied(path))
        if path.exists() and any(p.name.startswith(CHUNK_PREFIX) for p in path.iterdir()):
            raise CaptureError(f"{path}: holds chunk folders but no {MANIFEST}; refusing to mix scans")
        if path.exists() and (others := sorted(p.name for p in path.iterdir())):
            # A capture's folder is the capture: files of another kind in it would be mixed into it, and removing
            # the capture later would take them along.
            shown = ", ".join(others[:3]) + (f" and {len(others) - 3} more" if len(others) > 3 else "")
            raise CaptureError(f"{path}: holds other files ({shown}); a capture needs a new or empty folder")
        if not (isinstance(chunk_size, int) and 1 <= chunk_size <= 1_000_000):
            raise CaptureError(f"chunk size {chunk_size} must be an integer in [1, 1000000]")
        sensor.validate()
        check_json({"rig": rig, "schedule": schedule, "scene": scene}, f"{path / MANIFEST}")
        he = np.eye(4) if hand_eye is None else check_poses(np.asarray(hand_eye, float)[None], "hand-eye")[0]
        planned = None if planned_poses is None else check_poses(np.asarray(planned_poses, dtype=np.float64),
                                                                 "planned poses")
        manifest = {
            "format": FORMAT,
            "version": VERSION,
            "scan_id": scan_id or path.name,
            "state": "running",
            "reason": None,
            "created_utc": utc_now(),
            "updated_utc": utc_now(),
            "sensor": sensor.to_dict(),
            "rig": rig or {},
            "hand_eye": he.tolist(),
            "schedule": schedule or {},
            "planned_poses": None if planned_poses is None else int(len(planned_poses)),
            "frames_per_pose": int(frames_per_pose),
            "chunk_size": chunk_size,
            "scene": scene or {},
        }
        check_json(manifest, f"{path / MANIFEST}")  # fail before anything is written
        made = not path.exists()
        path.mkdir(parents=True, exist_ok=True)
        lock = None
        try:
            lock = _take_writer_lock(path)
            if planned is not None:
                _write(save_npy_durable, path / SCHEDULE, planned)
            _write(write_json_atomic, path / MANIFEST, manifest)
            _write(fsync_dir, path.parent)
        except BaseException:
            # A full disk or Ctrl-C here would leave files that make the rerun refuse the folder ("holds other
            # files", "not finished"): the folder was empty or new (checked above), so all that is in it is ours.
            _release_writer_lock(lock)
            _undo_create(path, made)
            raise
        return cls(path, manifest, sensor, 0, 0, set(), lock=lock)

    @classmethod
    def resume(cls, path, known: ChunkBook | None = None) -> "CaptureWriter":
        """Reopen a scan to continue it: drop half-written chunks, count what was published, list what is missing
        before the first unpublished pose (`retakes`: a damaged chunk moved out), state -> running. A pause stays
        recorded (`paused`, and its reason) until the scan goes on (`set_state`): a daemon reopens a capture to take
        it over before it has checked that it can, and a takeover refused or cut short must leave the operator's
        pause in place. CaptureError when the missing measurements cannot be put back in pose order, or a chunk
        cannot be read. `known`: the `book` of an earlier writer of this capture; every chunk it lists whose files
        are unchanged (`chunk_stamp`) is taken as it read it, every other one is read whole (and checked).
        CaptureError, before anything is touched, when another process holds the capture's writer lock: it is writing
        the capture."""
        path = Path(path)
        reader = CaptureReader(path)
        # Before anything is dropped or written: a capture another process writes is left as it is.
        lock = _take_writer_lock(path)
        try:
            reader = CaptureReader(path)  # read again under the lock: a writer that closed meanwhile may have written
            _drop_temporary(path)  # half-written chunks and manifests of a writer that died
            book = ChunkBook(path, (reader.sensor.n_zones, reader.sensor.n_bins))
            if known is not None and (Path(known.path) != path or tuple(known.shape) != book.shape):
                known = None  # another capture's, or checked against another sensor: read every chunk
            names = reader.chunk_names()
            held = []
            for name in names:
                stamp = chunk_stamp(os.path.join(path, name))  # before the read: a change after it shows next time
                record = known.unchanged(name, stamp) if known is not None else None
                if record is None:
                    record = ChunkRecord(stamp, tuple(held_frames(reader.read_chunk(name).meta)))
                if record.stamp is not None:
                    book.chunks[name] = record
                held.append((chunk_index(name), list(record.held)))
            stock = count_stock(held, reader.manifest, path)
            next_chunk = (chunk_index(names[-1]) + 1) if names else 0
            manifest = dict(reader.manifest)
            manifest.update(state="running", reason=manifest.get("reason") if "paused" in manifest else None,
                            updated_utc=utc_now())
            schedule = reader.planned_poses()
            if schedule is not None:
                # `replace_schedule` writes schedule.npy first and the manifest's count after it: a writer that died
                # between the two (a crash, a full disk) left the file's count, which the daemon's resume follows.
                manifest["planned_poses"] = int(len(schedule))
            _write(write_json_atomic, path / MANIFEST, manifest)
            return cls(path, manifest, reader.sensor, next_chunk, stock.published, set(stock.poses),
                       list(stock.retakes), book, lock=lock)
        except BaseException:
            _release_writer_lock(lock)
            raise

    # ---- writing -------------------------------------------------------------------------------------------------
    @property
    def chunk_size(self) -> int:
        return int(self.manifest["chunk_size"])

    @property
    def next_pose_index(self) -> int:
        """First pose index not yet published (poses are published in order)."""
        return max(self.published_pose_indices) + 1 if self.published_pose_indices else 0

    def append(self, m: Measurement) -> None:
        """Buffer one measurement; publishes a chunk when the buffer reaches the chunk size."""
        checked = self._checked(m)
        if self._buffer and (self._buffer[0].reference is None) != (checked.reference is None):
            self.flush()  # a chunk either has reference histograms for all its measurements or for none
        self._buffer.append(checked)
        if len(self._buffer) >= self.chunk_size:
            self.flush()

    def _checked(self, m: Measurement) -> Measurement:
        """A measurement as it is stored (counts as uint32, pose as float64), after checking it against the sensor
        model; CaptureError naming the pose and frame otherwise."""
        where = f"{self.path.name} pose {m.pose_index} frame {m.frame}"
        for key in ("pose_index", "frame"):
            v = getattr(m, key)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 0):
                raise CaptureError(f"{where}: {key} {v!r} must be an integer >= 0")
        hist = to_counts(m.hist, where)
        if hist.shape != (self.sensor.n_zones, self.sensor.n_bins):
            raise CaptureError(f"{where}: histogram shape {hist.shape}, expected "
                               f"({self.sensor.n_zones}, {self.sensor.n_bins})")
        pose = check_poses(np.asarray(m.pose, dtype=np.float64)[None], where)[0]
        ref = None
        if m.reference is not None:
            ref = to_counts(m.reference, where + " reference")
            if ref.shape != (self.sensor.n_bins,):
                raise CaptureError(f"{where}: reference shape {ref.shape}, expected ({self.sensor.n_bins},)")
        if not isinstance(m.meta, dict):
            raise CaptureError(f"{where}: meta is a {type(m.meta).__name__}, expected a dict")
        check_json(m.meta, where + " meta")
        return Measurement(hist, pose, int(m.pose_index), int(m.frame), ref, dict(m.meta))

    def flush(self) -> str | None:
        """Publish the buffered measurements as one chunk; returns its name (None when the buffer was empty)."""
        if not self._buffer:
            return None
        name = self._publish_chunk(self._next_chunk, self._buffer)
        self._next_chunk += 1
        self._buffer = []
        return name

    def take_stock(self) -> list[str]:
        """The chunks this writer published or read (`book`) that are gone from the folder now (moved out or deleted
        while the scan ran), by name; what they held is owed again (`retakes`, in pose order, as `resume` lists
        it), so that the scan is complete only once it is taken again. [] when none is gone. CaptureError when the
        folder cannot be listed (it is gone) or the frames cannot be put back in order."""
        try:
            present = {entry.name for entry in os.scandir(self.path) if entry.name.startswith(CHUNK_PREFIX)}
        except OSError as exc:
            raise CaptureError(f"{self.path}: cannot list the scan's folder ({exc.strerror or exc})") from None
        gone = sorted(name for name in self.book.chunks if name not in present)
        if not gone:
            return []
        for name in gone:
            del self.book.chunks[name]
        kept = [(chunk_index(name), list(record.held)) for name, record in sorted(self.book.chunks.items())]
        stock = count_stock(kept, self.manifest, self.path)
        self.retakes = list(stock.retakes)
        self.n_published = stock.published
        self.published_pose_indices = set(stock.poses)
        return gone

    def publish_retake(self, retake: Retake, measurements: list[Measurement]) -> None:
        """Publish the measurements taken again for `retake` (its pose's missing frames, in its order) under its
        chunk numbers (the next ones when it has none); then it is no longer owed."""
        got = [(int(m.pose_index), int(m.frame)) for m in measurements]
        if retake not in self.retakes or got != [(retake.pose, f) for f in retake.frames]:
            raise CaptureError(f"{self.path.name}: measurements {got} do not retake pose {retake.pose} frames "
                               f"{list(retake.frames)}")
        if retake.chunks is None:
            for m in measurements:
                self.append(m)
            self.flush()
        else:
            checked = [self._checked(m) for m in measurements]
            size = -(-len(checked) // len(retake.chunks))
            for k, number in enumerate(retake.chunks):
                batch = checked[k * size:(k + 1) * size]
                if len({m.reference is None for m in batch}) > 1:
                    raise CaptureError(f"{self.path.name} pose {retake.pose}: reference histograms for some of its "
                                       f"frames only")
                self._publish_chunk(number, batch)
        self.retakes.remove(retake)

    def _publish_chunk(self, number: int, buf: list[Measurement]) -> str:
        """Publish `buf` as chunk `number` (see the module docstring); returns its name. A published chunk never
        changes: a number already taken is refused."""
        name = chunk_name(number)
        if (self.path / name).exists():
            raise CaptureError(f"{self.path / name}: already published; a chunk is never replaced")
        tmp = self.path / f"{TMP_PREFIX}{name}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        meta = {"measurements": [{**m.meta, "pose_index": m.pose_index, "frame": m.frame} for m in buf]}
        writes = [(save_npy_durable, tmp / "hists.npy", np.stack([m.hist for m in buf])),
                  (save_npy_durable, tmp / "poses.npy", np.stack([m.pose for m in buf])),
                  (write_durable, tmp / "meta.json",
                   json.dumps(strict_json(meta), allow_nan=False).encode())]
        if buf[0].reference is not None:
            writes.append((save_npy_durable, tmp / "reference.npy", np.stack([m.reference for m in buf])))
        _together(writes)
        _write(fsync_dir, tmp)
        os.rename(tmp, self.path / name)
        self.book.record(name, [(m.pose_index, m.frame) for m in buf])
        _write(fsync_dir, self.path)
        self.n_published += len(buf)
        self.published_pose_indices.update(m.pose_index for m in buf)
        return name

    def replace_schedule(self, planned_poses: np.ndarray) -> None:
        """Replace schedule.npy atomically (temp file, fsync, rename, fsync the folder): a scan that chooses its poses
        as it goes (adaptive) rewrites the rows it has not published. A different number of poses (a scan that ends
        early) is recorded in the manifest's planned_poses too, after the file. Only a change of that number writes
        the manifest: replacing the rows alone may run beside this writer's publishing, on another thread."""
        planned = check_poses(np.asarray(planned_poses, dtype=np.float64), "planned poses")
        tmp = self.path / f"{TMP_PREFIX}{SCHEDULE}"
        _write(save_npy_durable, tmp, planned)
        os.replace(tmp, self.path / SCHEDULE)
        _write(fsync_dir, self.path)
        if self.manifest.get("planned_poses") != len(planned):
            self.manifest.update(planned_poses=int(len(planned)), updated_utc=utc_now())
            _write(write_json_atomic, self.path / MANIFEST, self.manifest)

    def set_state(self, state: str, reason: str | None = None, **extra) -> None:
        """Record the scan's state (and why) in the manifest, atomically. The reason is stored on one line, as the
        format defines it, whoever passed it (`ctl abort --reason` may carry line breaks)."""
        if state not in STATES:
            raise CaptureError(f"state {state!r} is not one of {STATES}")
        if state == "complete" and self.retakes:  # "complete" promises every pose 0 .. P - 1 (capture_format.md)
            raise CaptureError(f"{self.path}: not complete: pose(s) {', '.join(str(r.pose) for r in self.retakes)} "
                               f"lack frames that were never taken again")
        planned = self.manifest.get("planned_poses")
        if state == "complete" and planned is not None and (self._buffer or self.next_pose_index < planned):
            raise CaptureError(f"{self.path}: not complete: {self.next_pose_index} of {planned} planned poses "
                               f"published" + (" (measurements still buffered: finish() publishes them)"
                                               if self._buffer else ""))
        if isinstance(reason, str):
            reason = fold(reason)
        check_json({"reason": reason, **extra}, f"{self.path / MANIFEST}")
        self.manifest.pop("paused", None)  # a pause holds only until the next state is recorded
        self.manifest.update(state=state, reason=reason, updated_utc=utc_now(), **extra)
        _write(write_json_atomic, self.path / MANIFEST, self.manifest)

    def abandon(self, doing: str, exc: BaseException) -> None:
        """After `exc` stopped a writer that cannot be resumed (a simulation, an import): drop the buffer and mark the
        capture aborted with why. Best effort: on a full disk the manifest may not be writable either, and `exc` is
        the error to report, so a failure here is swallowed."""
        self._buffer = []
        _drop_temporary(self.path)  # frees a half-written chunk's space: the manifest may fit on a full disk then
        if isinstance(exc, KeyboardInterrupt):
            reason = f"{doing} interrupted"
        elif isinstance(exc, OSError) and exc.filename and exc.strerror:
            reason = f"{doing} failed: {exc.filename}: {exc.strerror}"
        else:
            reason = f"{doing} failed: {one_line(exc)}"
        try:
            self.set_state("aborted", reason)
        except (OSError, CaptureError):
            pass

    def finish(self, state: str = "complete", reason: str | None = None) -> None:
        """Flush and mark the scan complete (or aborted, with a reason)."""
        self.flush()
        self.set_state(state, reason)

    def __enter__(self) -> "CaptureWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self.flush()
        finally:
            self.close()
