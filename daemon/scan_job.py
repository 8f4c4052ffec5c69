"""One scan in the daemon's hands: its folder, plan and progress; scan names; finding a scan a crash interrupted.

A scan named N lives in `<captures>/N/` (docs/capture_format.md). Its `schedule.npy` holds the planned sensor poses in
visiting order and `scan.json` the scan settings, so a restarted daemon can continue it at the first pose not yet
published. The daemon marks the scans it writes (`rig.writer` = WRITER in the manifest) and takes over only those:
another tool's interrupted capture under the captures root (say `spadscan simulate --out <captures>/x`) is never driven.

An abort the manifest could not take (a full disk) is kept in the scan folder's `abort-pending.json` (ABORT_PENDING)
where it can be: an empty file needs no data block on a full disk. Its reason goes into the file where there is room
for it (at once, or on a later try), and meanwhile into the name of an empty file beside it (ABORT_REASON_PREFIX: a
name needs no data block either), so that a daemon restarted before room comes back still records the operator's
reason. A scan holding one is never taken over; the next daemon records the abort in `scan.json` and removes both.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import logging
import os
import re
import time
from collections import Counter, deque
from dataclasses import dataclass, field, fields
from pathlib import Path
from urllib.parse import quote, unquote

import numpy as np

from spadscan.protocol.capture_format import MANIFEST, chunk_index, fsync_dir, read_json
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import (INTERRUPTED, CaptureWriter, ChunkBook, Stock, chunk_stamp, count_stock,
                                              held_frames, writer_lock_held)
from spadscan.protocol.errors import CaptureError, ConfigError
from spadscan.protocol.iso_time import parse_utc, utc_now
from spadscan.protocol.sensor_model import SensorModel

from .config import ScanConfig, scan_with
from .root_lock import LOCK_NAME as ROOT_LOCK_NAME
from .scan_plan import tcp_from_sensor
from .sensor_differences import NO_DIFFERENCE, sensor_differences

log = logging.getLogger("spadscan.daemon")
WRITER = "spadscan-daemon"
"""The manifest's rig.writer of every scan the daemon writes."""
ABORT_PENDING = "abort-pending.json"
"""In a scan folder: the scan was aborted, but its scan.json could not record it yet ({"reason", "since_utc"}, or
empty when the disk had no room for even that)."""
ABORT_REASON_PREFIX = "abort-pending.reason="
"""In a scan folder beside an ABORT_PENDING file whose record did not fit: an empty file named this plus the abort's
reason, percent-encoded (cut to REASON_NAME_MAX characters, ending in '...')."""
REASON_NAME_MAX = 200  # characters of encoded reason in that name: with the prefix, well under a name's 255 bytes
_REASON_SAFE = " ,;:()'!@+="  # kept as they are in that name (letters, digits and _.-~ always are)
DEFAULT_ABORT_REASON = "aborted by user"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,99}")


def check_scan_name(name, root: Path) -> str:
    """A scan name that stays inside the captures root: letters, digits and . _ + -, not hidden, <= 100 chars."""
    if not isinstance(name, str) or not name:
        raise ConfigError("scan name must be a non-empty string")
    if not _NAME.fullmatch(name) or name in (".", ".."):
        raise ConfigError(f"scan name {name!r} must be 1-100 letters, digits or . _ + - and not start with . _ + - "
                          f"(no '/', no '..', no hidden names)")
    root = Path(root).resolve()
    if (root / name).resolve().parent != root:
        raise ConfigError(f"scan name {name!r} escapes the captures root {root}")
    return name


def name_taken(name: str, root: Path) -> str:
    """Why a new scan cannot be named `name` in captures root `root`, where something by that name is: a scan, or
    what else (`ctl scan --name X` called a file or an empty folder X a scan that exists, where `ctl wait X` said
    there is no scan named X)."""
    path = Path(root) / name
    if (path / MANIFEST).is_file():
        return f"scan {name!r} already exists in {root} (choose another name)"
    what = "a folder that holds no scan" if path.is_dir() else "a file, not a scan"
    return f"{name!r} already exists in {root}, {what} (choose another name)"


def default_scan_name(root: Path) -> str:
    """scan-YYYYMMDD-HHMMSS (local time), with a suffix when that folder exists."""
    base = "scan-" + _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    name, k = base, 1
    while (Path(root) / name).exists():
        k += 1
        name = f"{base}-{k}"
    return name


@dataclass
class ScanJob:
    """A scan being run. sensor_poses / tcp_poses: (P, 4, 4) in visiting order; next_pose: poses published so far."""

    name: str
    path: Path
    scan: ScanConfig
    sensor_poses: np.ndarray
    tcp_poses: np.ndarray
    hand_eye: np.ndarray
    writer: CaptureWriter | None = None
    chunk_book: ChunkBook | None = None
    """The chunks of the capture that this daemon's writers read or published (`CaptureWriter.book`): kept while a
    fault has dropped the writer, so that reopening it (`reopen`) reads again only the chunks that changed."""
    next_pose: int = 0
    frames: int = 0
    dropped: int = 0
    reason: str | None = None
    paused_for: str | None = None
    """Why the scan is paused in the first place, while something found since keeps it paused too (a takeover, or a
    resume refused, that found no room on the disk; a resume refused for the sensor's link): the reason recorded in
    the capture when a daemon took the scan over (the operator's pause, a fault's), or the takeover's own note that
    it was interrupted, or the operator's pause (`ctl pause`) of a scan that waited after a takeover. `reason` says
    it first, then what stands in the way now; a pause records it alone in the capture (the next daemon checks the
    disk and the link again itself). None once the scan goes on."""
    interrupted: bool = False
    """Paused only because a takeover found the scan interrupted: no one and nothing paused it. Its capture records
    the pause as such (`paused.kind` INTERRUPTED), so that the next daemon may go on by itself. False once it goes
    on, or once the operator pauses it (`ctl pause`: the wait becomes a pause, and is recorded as one)."""
    blocked: str | None = None
    """Why this scan cannot resume (e.g. the rig's hand-eye changed); None when it can."""
    preset_note: str | None = None
    """How the installed spadscan's preset differs from the one the scan was planned with, where that does not stop
    it (a real sensor's histograms do not depend on it: the scan goes on with the model its capture records), for
    `ctl status`; None when it does not differ."""
    in_flight: int | None = None
    """The pose being captured, or captured and not yet published (the runner finishes it before it pauses)."""
    arm_fix: str | None = None
    """What the arm needs before its next move after a fault: 'reconnect' (lost link), 'clear' (arm fault) or None."""
    controller_checked: bool = False
    """The arm's controller has been asked about the poses still to come since the scan last started or resumed."""
    started: float = field(default_factory=time.monotonic)
    """When this daemon started the scan or took it over (monotonic s): status's `elapsed_s` counts from here."""
    started_utc: str | None = None
    """When the scan began, as its scan.json records it (`created_utc`); None when scan.json holds no readable
    one."""
    earlier_s: float | None = None
    """Seconds from `started_utc` to `started` (for a scan taken over: the earlier daemons' time and the time none
    ran); None when `started_utc` is. Set by `count_from`."""
    history: deque = field(default_factory=lambda: deque(maxlen=256))
    """(monotonic s, frames published) after each pose and at each (re)start of scanning (`mark_scanning`), for the
    rate."""
    scanning_since: float | None = None
    """When the scan last began taking frames (started or resumed; monotonic s), or None before: the rate counts
    back no further, so a pause does not drag it down after the resume."""
    chooser: object | None = None
    """An adaptive scan's `adaptive.ViewChooser`; None for a planned scan."""
    choices: dict = field(default_factory=dict)
    """Pose index -> why it was taken (adaptive scans: the `view_choice` record of its measurements)."""
    view_counts: Counter = field(default_factory=Counter)
    """Poses published by why they were taken (adaptive scans): initial, adaptive, fallback."""
    ended_early: str | None = None
    """Why an adaptive scan ends before its last planned pose (the live reconstruction converged), or None."""
    owed: list[int] = field(default_factory=list)
    """The poses the capture lacks before its first unpublished one (its writer's `retakes`, to be taken again), as
    last read: kept while a fault has dropped the writer, so that status still lists them."""
    owed_note: str | None = None
    """Why a paused scan's progress (`next_pose`, `frames`, `owed`) is as last counted, not as its resume will count
    it (`stock_on_disk`: a chunk new or changed since the daemon read it is read at the resume), or None."""
    way_on: bool = False
    """The retake's way along the scan's path (back to the poses owed, forward to the last published pose) is
    unfinished: the next run walks it on before the scan's next pose (`ScanRunner._retake`)."""
    way_at: tuple[int, str, str] | None = None
    """Where the retake's way has the arm: (pose, "moving to" or "at", "back" or "forward"); None off the way."""
    taken_over: bool = False
    """Taken over from an earlier daemon, and no run has looked yet where the arm stands (a stop on the retake's
    way forward leaves it on the scan's path before its last published pose, which no record says)."""
    winding_down: object | None = None
    """The scan task's wind-down (an asyncio future: abort or shutdown), once begun; None before."""

    @property
    def n_poses(self) -> int:
        return len(self.sensor_poses)

    def count_from(self, created_utc) -> None:
        """Date the scan's start by its scan.json's `created_utc` (ISO 8601; UTC when it names no zone). The wall
        clock is read once, here: from then on the time since the start is counted on the monotonic clock, so that a
        wall clock set later (NTP) does not move it. A start in the future (a clock set back since) counts as now."""
        begun = parse_utc(created_utc)
        if begun is None:
            self.started_utc, self.earlier_s = None, None
            return
        wall, mono = _dt.datetime.now(_dt.timezone.utc), time.monotonic()
        self.started_utc = created_utc
        self.earlier_s = max(0.0, (wall - begun).total_seconds() - (mono - self.started))

    def scan_elapsed_s(self, now: float | None = None) -> float | None:
        """Seconds since the scan began (`started_utc`), across daemon restarts and takeovers, pauses and the time
        no daemon ran included, at `now` (time.monotonic(); default: read here); None when scan.json does not say
        when it began."""
        if self.earlier_s is None:
            return None
        return self.earlier_s + ((time.monotonic() if now is None else now) - self.started)

    def reopen(self) -> CaptureWriter:
        """The capture's writer, reopened (`CaptureWriter.resume`; on the writer's thread): a chunk read or published
        by an earlier writer of this daemon is read again only where its files changed (`chunk_book`); one moved out
        is missed, one added is read whole, as ever."""
        writer = CaptureWriter.resume(self.path, known=self.chunk_book)
        self.chunk_book = writer.book
        return writer

    def record_progress(self, writer: CaptureWriter) -> None:
        self.next_pose = writer.next_pose_index
        self.frames = writer.n_published
        self.owed = [r.pose for r in writer.retakes]
        self.owed_note = None  # (counted from the capture itself)
        self.history.append((time.monotonic(), self.frames))

    def count_published(self) -> None:
        """Progress read from the capture folder alone (no writer, nothing written): for a scan whose writer could
        not be reopened. Counted as the writer's reopening counts it (`count_stock`), so that status lists the poses
        owed while the operator makes room (CaptureError, as there, when they cannot be put back in pose order)."""
        reader = CaptureReader(self.path)
        held = [(chunk_index(name), held_frames(reader.read_chunk(name).meta)) for name in reader.chunk_names()]
        self.record_stock(count_stock(held, reader.manifest, self.path))

    def record_stock(self, stock: Stock) -> None:
        """Progress as the capture's folder holds it (`count_stock`), where no writer counts it."""
        self.next_pose = stock.next_pose
        self.frames = stock.published
        self.owed = [r.pose for r in stock.retakes]

    def stock_on_disk(self) -> tuple[Stock | None, str | None]:
        """What a paused scan's resume finds in its folder as it stands now (the pose it goes on at, the frames
        published, the poses it takes again), from the chunk book's records of the chunks still there, counted as
        the resume counts them (`count_stock`, its chunks listed as `CaptureReader.chunk_names` lists them): a chunk
        moved out during the pause, the newest included, shows at once, not only once the resume has reopened the
        capture. No chunk is read: (stock, None), or (None, why only the resume can count) where the capture has not
        been read yet, its folder cannot be listed, or a chunk is new or changed since the daemon read it (the
        resume reads it). CaptureError when the folder's manifest cannot be read, or the frames left cannot be put
        back in pose order (the resume says the same)."""
        book = self.chunk_book
        if book is None:
            return None, "the capture has not been read yet: `spadscan ctl resume` counts its chunks"
        reader = CaptureReader(self.path)
        try:
            present = reader.chunk_names()
        except OSError as exc:
            return None, f"cannot list the scan's folder ({exc.strerror or exc})"
        known = dict(book.chunks)  # (a copy: the writer's thread may record a chunk meanwhile)
        unread = [name for name in present
                  if name not in known or known[name].stamp != chunk_stamp(os.path.join(self.path, name))]
        if unread:  # what they hold is not known without reading them
            them = "it" if len(unread) == 1 else "them"
            return None, (f"{', '.join(unread[:3])}{' and more' if len(unread) > 3 else ''} changed since the daemon "
                          f"read {them}: `spadscan ctl resume` reads {them} and counts again")
        held = [(chunk_index(name), list(known[name].held)) for name in present]
        return count_stock(held, reader.manifest, self.path), None

    def count_choices(self) -> None:
        """view_counts read from the published measurements' meta (after a restart)."""
        self.view_counts = Counter()
        reader = CaptureReader(self.path)
        seen = set()  # each pose once, whichever chunks hold its frames (a pose taken again in part is in two)
        for name in reader.chunk_names():
            for m in read_json(self.path / name / "meta.json").get("measurements", []):
                choice = m.get("view_choice") if isinstance(m, dict) else None
                if isinstance(choice, dict) and m.get("pose_index") not in seen:
                    seen.add(m.get("pose_index"))
                    self.view_counts[str(choice.get("why"))] += 1

    def mark_scanning(self) -> None:
        """The scan begins taking frames (it starts, or resumes after a pause): the rate is counted from here."""
        self.scanning_since = time.monotonic()
        self.history.append((self.scanning_since, self.frames))

    def rate_hz(self, window_s: float = 10.0) -> float:
        """Frames published per second over the last window_s seconds, counted back from now, not from the last
        publication: a scan whose frames stop coming (a silent sensor) shows its rate falling, not the rate it had.
        The window reaches no further back than the scan's last start or resume (a pause's time is no time spent
        scanning); 0.0 before it has begun. The rate of a scan that is not taking frames at all (paused) is for the
        caller to leave out."""
        now = time.monotonic()
        if self.scanning_since is None:
            return 0.0
        begin = max(now - window_s, self.scanning_since)
        before = [(t, f) for t, f in self.history if t <= begin]
        t0, f0 = before[-1] if before else (self.history[0] if self.history else (begin, self.frames))
        t0 = max(t0, begin)  # the frames counted at t0 were all published by `begin`: the window starts there
        return (self.frames - f0) / (now - t0) if now > t0 else 0.0


def written_by_daemon(manifest: dict) -> bool:
    """Whether a capture's manifest says the daemon wrote it (rig.writer = WRITER): only those does it take over or
    end."""
    rig = manifest.get("rig")
    return isinstance(rig, dict) and rig.get("writer") == WRITER


def find_interrupted(root: Path) -> list[Path]:
    """The daemon's scan folders under root whose manifest says 'running' (a crash or stop left them), the one updated
    last first: the one a restarted daemon takes over. 'running' captures the daemon did not write (no rig.writer =
    WRITER) are logged and skipped."""
    found: list[tuple[str, Path]] = []
    root = Path(root)
    if not root.is_dir():
        return []
    for d in root.iterdir():
        m = d / MANIFEST
        if d.name.startswith(".") or not m.is_file():
            continue
        try:
            manifest = read_json(m)
        except CaptureError:
            continue
        if manifest.get("state") != "running":
            continue
        if (d / ABORT_PENDING).exists():  # aborted: the manifest could not say so yet (recover records it)
            continue
        if not written_by_daemon(manifest):
            log.warning("not taking over %s: its capture says 'running' but was not written by the daemon "
                        "(no rig.writer = %r in %s)", d, WRITER, MANIFEST)
            continue
        found.append((str(manifest.get("updated_utc", "")), d))
    return [d for _, d in sorted(found, key=lambda pair: (pair[0], pair[1].name), reverse=True)]


def note_abort_pending(path: Path, reason: str) -> bool:
    """Keep an abort that scan.json could not take in the scan folder's ABORT_PENDING file: created empty first (on
    a full disk an empty file still fits: it needs no data block), then its record written where there is room. A
    record that did not fit whole is cut back to empty, which still says 'aborted', and the reason goes into the name
    of an empty file beside it (ABORT_REASON_PREFIX). Called again (each retry), it writes the record into a file
    that lacks one; a file holding its record is never rewritten. Returns whether the file is there (False on a
    read-only disk). The scan's writer must not be writing meanwhile."""
    marker = Path(path) / ABORT_PENDING
    if _recorded_reason(marker) is not None:  # kept whole already (maybe an earlier daemon's): nothing to add
        return True
    record = json.dumps({"reason": reason, "since_utc": utc_now()}).encode()
    try:
        fd = os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)  # it held no record: nothing is lost
    except OSError:  # a read-only disk: an empty file made before it turned read-only still keeps the abort
        return marker.is_file()
    try:
        whole = _write_whole(fd, record)
        with contextlib.suppress(OSError):
            if not whole:
                os.ftruncate(fd, 0)
            os.fsync(fd)
    finally:
        os.close(fd)
    if not whole:
        _name_reason(Path(path), reason)
    with contextlib.suppress(OSError):
        fsync_dir(Path(path))
    return True


def _write_whole(fd: int, data: bytes) -> bool:
    """Write `data` at the start of the open file `fd`; whether all of it was written (a full disk writes part)."""
    try:
        return os.write(fd, data) == len(data)
    except OSError:
        return False


def _recorded_reason(marker: Path) -> str | None:
    """The reason an ABORT_PENDING file's record holds; None when it holds none (empty, cut, unreadable, absent)."""
    try:
        reason = json.loads(marker.read_text(encoding="utf-8")).get("reason")
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        return None
    return reason if isinstance(reason, str) and reason else None


def _name_reason(path: Path, reason: str) -> None:
    """Keep `reason` in the name of an empty file in the scan folder (best effort: a name needs no data block, but
    a directory with no room left for one more name refuses it)."""
    encoded = quote(reason, safe=_REASON_SAFE)
    if len(encoded) > REASON_NAME_MAX:
        cut, room = [], REASON_NAME_MAX - 3
        for ch in reason:
            q = quote(ch, safe=_REASON_SAFE)
            if len(q) > room:
                break
            cut.append(q)
            room -= len(q)
        encoded = "".join(cut) + "..."
    with contextlib.suppress(OSError):
        os.close(os.open(path / (ABORT_REASON_PREFIX + encoded), os.O_WRONLY | os.O_CREAT, 0o644))


def _named_reason(path: Path) -> str | None:
    """The reason kept in the name of an empty file beside ABORT_PENDING (see `_name_reason`), or None."""
    with contextlib.suppress(OSError):
        for p in sorted(Path(path).iterdir()):
            if p.name.startswith(ABORT_REASON_PREFIX) and len(p.name) > len(ABORT_REASON_PREFIX):
                return unquote(p.name[len(ABORT_REASON_PREFIX):])
    return None


def abort_pending(path: Path) -> str | None:
    """The reason of the abort kept in the scan folder's ABORT_PENDING file (its record, else the name beside it,
    else DEFAULT_ABORT_REASON); None when there is no such file."""
    marker = Path(path) / ABORT_PENDING
    if not marker.is_file():
        return None
    return _recorded_reason(marker) or _named_reason(Path(path)) or DEFAULT_ABORT_REASON


def clear_abort_pending(path: Path) -> None:
    """Remove the ABORT_PENDING file (and a name that kept its reason) once scan.json says the scan ended (best
    effort: a file left over is removed by the next daemon, which finds the scan already ended)."""
    with contextlib.suppress(OSError):
        for p in Path(path).iterdir():
            if p.name.startswith(ABORT_REASON_PREFIX):
                p.unlink(missing_ok=True)
        (Path(path) / ABORT_PENDING).unlink(missing_ok=True)
        fsync_dir(Path(path))


def find_abort_pending(root: Path) -> list[Path]:
    """The scan folders under root that hold an ABORT_PENDING file."""
    root = Path(root)
    if not root.is_dir():
        return []
    return sorted(d for d in root.iterdir() if not d.name.startswith(".") and (d / ABORT_PENDING).is_file())


def interrupted_scan(root: Path, name: str) -> Path:
    """The folder of scan `name` under root if it is one of the daemon's scans left 'running' (interrupted, or one
    that could not be taken over); a ConfigError says why not otherwise."""
    path = Path(root) / check_scan_name(name, root)
    if not (path / MANIFEST).is_file():
        raise ConfigError(f"no scan named {name!r} in {root}")
    try:
        manifest = read_json(path / MANIFEST)
    except CaptureError as exc:
        raise ConfigError(f"scan {name!r}: {exc}") from None
    state = manifest.get("state")
    if state != "running":
        raise ConfigError(f"scan {name!r} has already ended ({state})")
    if not written_by_daemon(manifest):
        raise ConfigError(f"scan {name!r} was not written by the daemon (no rig.writer = {WRITER!r} in "
                          f"{MANIFEST}); it is not the daemon's to end")
    return path


def damaged_chunks(path: Path) -> tuple[list[str], list[str], list[str]]:
    """(every chunk, those that cannot be read: torn or zeroed files after a power cut, those this user may not read:
    another owner, a mode) of the capture at `path`. The last are kept apart: their content may be intact, and the
    advice for a damaged chunk (move it out) would throw good data away."""
    try:
        reader = CaptureReader(path)
        names = reader.chunk_names()
    except (CaptureError, OSError):
        return [], [], []
    damaged, forbidden = [], []
    for name in names:
        read = reader.try_read_chunk(name)  # the reader's own verdict, so that this advice and its load agree
        if read.forbidden:
            forbidden.append(name)
        elif read.damaged:
            damaged.append(name)
    return names, damaged, forbidden


def way_out(path: Path) -> str:
    """What the operator can do about a scan that could not be taken over (reads its chunks: run it off the event
    loop): let the daemon read the chunks it may not, set its damaged chunks aside and resume it, or end it (every
    chunk stays)."""
    name = path.name
    if writer_lock_held(path):  # another daemon writes it: neither a resume nor an abort here may touch it
        return (f"leave it to that process, or stop it, then `spadscan ctl resume {name}` here (was the root's "
                f"{ROOT_LOCK_NAME} removed while it ran?)")
    end = f"or `spadscan ctl abort {name}` ends the scan as aborted, keeping every chunk"
    _, damaged, forbidden = damaged_chunks(path)
    steps = []
    if forbidden:
        steps.append(f"{', '.join(forbidden)} cannot be read by this user (permission denied): give the daemon's user "
                     f"read access (owner or mode; {'its' if len(forbidden) == 1 else 'their'} content may be intact, "
                     f"keep {'it' if len(forbidden) == 1 else 'them'} in place)")
    if damaged:
        # Whichever chunk it is: the resumed scan takes the poses the capture lacks again, going back along its path,
        # and publishes them in pose order (CaptureWriter.retakes), so that it ends complete with every pose.
        again = "its poses are taken again" if len(damaged) == 1 else "their poses are taken again"
        steps.append(f"{', '.join(damaged)} cannot be read: move {'it' if len(damaged) == 1 else 'them'} out of "
                     f"{path} ({again})")
    if not steps:
        return f"once that is fixed, `spadscan ctl resume {name}` takes it over; {end}"
    return f"{'; '.join(steps)}, then `spadscan ctl resume {name}`; {end}"


def load_job(path: Path, hand_eye_now: np.ndarray, *, sensor_now: SensorModel | None = None,
             rig_now: dict | None = None, scene_now: dict | None = None) -> ScanJob:
    """Reopen an interrupted scan's plan and settings (not its writer) from its folder.

    The plan's TCP poses come from the capture's own hand-eye; when the rig's hand-eye differs, the job is marked
    blocked (resuming would put the sensor elsewhere than planned). So it is when the rig's sensor differs from the
    one the capture records (sensor_now: the sensor model now; rig_now, scene_now: the rig and scene records a new
    capture would get): resuming would mix two sensors in one capture. So it is, too, when the installed spadscan's
    preset of the same name gives other numbers than the one the scan was planned with (an upgrade refitted it) and
    the sensor renders with the model (sim), or its zone or bin counts changed: then no key of the rig's can restore
    it, and the block names the spadscan version that started the scan (`started_by`). A real sensor's histograms do
    not depend on the preset's numbers (its driver checks only the zone and bin counts against them), and a resumed
    capture keeps the model it records: there the difference is a note (`ScanJob.preset_note`), not a block.
    """
    reader = CaptureReader(path)
    planned = reader.planned_poses()
    if planned is None:
        raise CaptureError(f"{path}: has no schedule.npy; cannot resume")
    known = {f.name for f in fields(ScanConfig)}
    stored = {k: v for k, v in reader.manifest.get("schedule", {}).items() if k in known}
    # A lag below 2 is refused now (every ranking is at least one pose old when the next pose is chosen), but a scan
    # planned before that must still resume: it ran as a planned scan, and 2 lets its rest use a fresh ranking.
    if isinstance(stored.get("next_views_max_lag"), int) and stored["next_views_max_lag"] < 2:
        stored["next_views_max_lag"] = 2
    try:
        scan = scan_with(ScanConfig(), stored, f"{path / MANIFEST} schedule")
    except ConfigError as exc:
        raise CaptureError(str(exc)) from None
    job = ScanJob(name=path.name, path=Path(path), scan=scan, sensor_poses=planned,
                  tcp_poses=tcp_from_sensor(planned, reader.hand_eye), hand_eye=reader.hand_eye)
    job.count_from(reader.manifest.get("created_utc"))
    changed = []
    if not np.allclose(reader.hand_eye, hand_eye_now, atol=1e-6):
        changed.append(f"the rig's [arm] hand_eye differs from the one scan {path.name!r} was planned with")
    diff = NO_DIFFERENCE if sensor_now is None else sensor_differences(reader, sensor_now, rig_now or {},
                                                                       scene_now or {})
    if diff.keys:
        changed.append(f"the rig's [sensor] differs from the one scan {path.name!r} was planned with "
                       f"({', '.join(diff.keys)})")
    job.blocked = block_reason(path.name, changed, reader.sensor.name, diff.preset if diff.preset_blocks else [],
                               started_by(reader.manifest))
    if diff.preset and not diff.preset_blocks:
        job.preset_note = preset_note(path.name, reader.sensor.name, diff.preset, diff.backend)
    return job


RIG_VERSION = "spadscan_version"
"""The rig record's key (scan.json `rig`) of the spadscan version that started the scan."""


def started_by(manifest: dict) -> str:
    """The spadscan version that started a capture, as a block says it: the one its rig record names, else the one
    installed when it began (`created_utc`: captures older than that record), else no more than that."""
    rig = manifest.get("rig")
    version = rig.get(RIG_VERSION) if isinstance(rig, dict) else None
    if isinstance(version, str) and version.strip():
        return f"spadscan {version.strip()}, which started it"
    begun = parse_utc(manifest.get("created_utc"))
    if begun is not None:
        return f"the spadscan version installed on {begun.astimezone(_dt.timezone.utc):%Y-%m-%d %H:%M} UTC"
    return "the spadscan version that started it"


def block_reason(name: str, changed: list[str], preset_name: str, preset: list[str],
                 started: str = "the spadscan version that started it") -> str | None:
    """Why scan `name` cannot resume, with what the operator can do; None when it can. `changed`: what differs in
    the rig (its config can restore it); `preset`: how the installed spadscan's preset `preset_name` differs from the
    one the scan was planned with (`preset_changes`), which only the spadscan version that started the scan gives
    (`started`, as `started_by` says it)."""
    abort = f"or abort the scan (`spadscan ctl abort {name}`)"
    if not preset:
        return "; ".join(changed) + f"; restore it to resume, {abort}" if changed else None
    said = f"this spadscan's `{preset_name}` preset differs from the one scan {name!r} was planned with: {_few(preset)}"
    finish = f"finish it with {started}"
    if changed:
        return "; ".join(changed + [said]) + f"; restore the rig and {finish}, {abort}"
    return f"{said}; {finish}, {abort}"


def preset_note(name: str, preset_name: str, preset: list[str], backend: str) -> str:
    """What `ctl status` says of a scan whose preset differs from the installed one where that does not stop it: a
    `backend` sensor's histograms do not depend on the model, and the capture keeps the one it records."""
    return (f"this spadscan's `{preset_name}` preset differs from the one scan {name!r} was planned with: "
            f"{_few(preset)}; the scan goes on with the sensor model its capture records ([sensor] backend "
            f"{backend!r}: the sensor's histograms do not depend on it)")


def _few(preset: list[str]) -> str:
    """The first PRESET_CHANGES_SHOWN of a preset's differences, then how many more."""
    shown = ", ".join(preset[:PRESET_CHANGES_SHOWN])
    if len(preset) > PRESET_CHANGES_SHOWN:
        shown += f" and {len(preset) - PRESET_CHANGES_SHOWN} more"
    return shown


def pause_before_block(reason: str | None, name: str) -> str | None:
    """A pause's reason recorded in scan `name`'s capture, less the block an earlier daemon found and said there
    (`block_reason`: its first part names what differs from the one the scan 'was planned with'), or None when
    nothing else was said. A daemon taking the scan over checks the rig and its presets afresh: a block since lifted
    (the rig restored, the spadscan version put back, one that no longer counts free text) is no pause of the
    operator's, and must not stand as one."""
    if reason is None:
        return None
    parts = reason.split("; ")
    mark = f"differs from the one scan {name!r} was planned with"
    first = next((i for i, part in enumerate(parts) if mark in part), None)
    if first is None:
        return reason
    return "; ".join(parts[:first]) or None


RESTARTED = "(daemon restarted)"
"""What a takeover's own note of an interrupted scan says after the pose it was interrupted at (`interrupted_at`)."""


def interrupted_at(progress: str) -> str:
    """How a daemon that took a scan over says it found it interrupted at pose `progress` (i/n): recorded as the
    scan's pause (of kind INTERRUPTED) while it waits for `ctl resume`."""
    return f"interrupted at pose {progress} {RESTARTED}"


def takeover_note(paused: dict) -> bool:
    """Whether scan.json's `paused` record is a takeover's own note that the scan was interrupted (its `kind` is
    INTERRUPTED), not a pause of the operator's or a fault's: no one paused the scan, so the next daemon goes on by
    itself where auto_resume allows. A kind this daemon does not know is taken for a pause: the arm does not move by
    itself. A record without a kind was written before it had one (`older_takeover_note`)."""
    kind = paused.get("kind")
    if kind is None:
        return older_takeover_note(paused.get("reason"))
    return kind == INTERRUPTED


OLDER_TAKEOVER_NOTE = re.compile(r"interrupted at pose \d+/\d+ \(daemon restarted\)(?=$|[;,])")
"""How a takeover's note began in a `paused` record written before records had a `kind`. Matched only there: that
wording is fixed (no newer daemon writes such a record: so it is spelled out here, not built from `interrupted_at`,
which may be reworded), and in those versions nothing else began so (`ctl pause` takes no reason, and no fault's
reason starts with it)."""


def older_takeover_note(reason) -> bool:
    """Whether the reason of a `paused` record without a `kind` (one written before records had it, by a daemon that
    took the scan over interrupted and waited for `ctl resume`) is that takeover's own note: a scan such a daemon
    left waiting, taken over after an update, still goes on by itself where auto_resume allows."""
    return isinstance(reason, str) and OLDER_TAKEOVER_NOTE.match(reason) is not None


PRESET_CHANGES_SHOWN = 3
"""How many of the fields in which a preset differs a block names (then "and N more")."""
