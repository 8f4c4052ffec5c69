"""The scans under a captures root as the dashboard lists them: state and progress, read with protocol's capture
reader, and remembered between polls so that a root of hundreds of finished scans costs a stat per scan per poll.

A finished scan never changes until its manifest does (published chunks are never rewritten), so its row is kept
until `scan.json` changes; a running scan's row is kept until its chunk listing changes too. `reads` counts the
files parsed, so that the cost of a poll can be checked without a clock.

A scan whose scan.json says running but that publishes no new pose is shown as stalled (`stalled`): its daemon may
have paused without being able to record the pause (a full disk), or hang. The rule is in `quiet_limit_s`.

A scan in hand may owe poses again: a resumed scan whose damaged chunk was moved out takes its poses again before its
next one (capture_format.md). They are counted from the frames its chunks hold, as the daemon's writer counts them
(protocol's `plan_retakes`), and its time left counts them as the daemon's `ctl status` does. Each chunk's records
are read once: published chunks never change.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import statistics
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from spadscan.protocol.capture_format import MANIFEST, chunk_index, read_json
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import held_frames, plan_retakes
from spadscan.protocol.errors import SpadscanError

from .paths import safe_path, url_path

RATE_FRAMES = 16
"""The frame rate is measured over (at most) this many of the last frames."""
STOP_FACTOR = 5.0
"""A move between two poses this many times the median one is a stop (a pause, a restart): the pace counts from after
it."""
MAX_PLOT_BINS = 256
"""Histograms are max-pooled to at most this many bins for the page's plot (a return stays visible)."""


@dataclass
class ScanRow:
    """One scan: its folder name under the root, state, poses published and planned (progress = their ratio)."""

    name: str
    state: str
    poses: int = 0
    planned: int | None = None
    progress: float | None = None
    updated_utc: str | None = None
    reason: str | None = None
    error: str | None = None
    """Why the capture cannot be read (a malformed capture is an error row, never a crash)."""
    note: str | None = None
    """Why the scan's files have no links (its folder is a link out of the root, which the server never serves)."""
    quiet_s: float | None = None
    """A stalled scan's seconds without news (no new pose, no write of its scan.json); None on any other row."""
    started_utc: str | None = None
    """When the scan began (its scan.json's created_utc): the page says how long it has been running."""
    config: str | None = None
    """The rig configuration of the daemon that recorded it (scan.json's rig.config), when it says: the page's hint
    that starts a daemon names it."""
    chunks: list[str] = field(default_factory=list, repr=False)
    mtime: float = 0.0
    published: list[float] = field(default_factory=list, repr=False)
    """When its last (at most PACE_POSES) chunks were published (unix seconds, oldest first): its recent pace."""
    owed: int | None = None
    """A scan in hand's poses before its last published one that lack frames (the daemon takes them again before its
    next pose); 0 on a scan not in hand (none is complete while it owes any), None where a chunk cannot be read."""

    def to_dict(self) -> dict:
        d = asdict(self)
        del d["chunks"], d["mtime"], d["published"]
        return d


IN_HAND = ("running", "paused")
"""A row's states of a scan still in hand (listed first; the page's "current" scan is the first of them)."""
INTERRUPTED = "interrupted"
"""A scan in hand whose daemon is gone (crashed, killed or stopped): scan.json still says running, but nothing
writes it. It takes no frames, so it has no frame rate; a daemon started on the root takes it over."""
NOT_TAKEN_OVER = "not_taken_over"
"""A scan in hand that the running daemon did not take over, by its own status (`spadscan ctl status`, where the
dashboard can ask it: `cannot_take_over`, `also_interrupted`): scan.json still says running, but nothing records it.
The reason is the daemon's own, with the way out."""
NO_DAEMON = "no daemon running"
STALLED = "stalled"
"""A scan whose scan.json says running but whose latest news is older than `quiet_limit_s` allows: its daemon may
be paused without having recorded it (it cannot write scan.json on a full disk) or stuck. It has no frame rate (its
last one is no longer true); `spadscan ctl status` says what the daemon is doing."""

PACE_POSES = 8
"""The pace of a scan is read from the publications of its last (at most) this many poses."""
QUIET_FACTOR = 5.0
QUIET_FLOOR_S = 120.0
"""See `quiet_limit_s`."""

JSON_KINDS = {int: "a whole number", str: "a string", dict: "an object"}


def _typed(mapping: dict, key: str, kind: type, where: str):
    """mapping[key], None when absent or null; a SpadscanError naming the field when it has another JSON type (the
    capture reader checks only what it reads itself, and one bad scan.json must not take the other rows down)."""
    value = mapping.get(key)
    if value is None or (isinstance(value, kind) and not isinstance(value, bool)):
        return value
    raise SpadscanError(f"{where}: {key} {json.dumps(value)[:40]} is not {JSON_KINDS[kind]}")


def _rig_config(manifest: dict, where: str) -> str | None:
    """The daemon's configuration file named in scan.json's rig (daemon/rig.py writes it), or None."""
    return _typed(_typed(manifest, "rig", dict, where) or {}, "config", str, f"{where} rig")


def _planned(manifest: dict, where: str) -> int | None:
    planned = _typed(manifest, "planned_poses", int, where)
    if planned is None:
        planned = _typed(_typed(manifest, "schedule", dict, where) or {}, "views", int, f"{where} schedule")
    return planned if planned is not None and planned > 0 else None


class ScanIndex:
    """The scans of one root, remembered between polls (not thread-safe: the server holds a lock)."""

    def __init__(self, root):
        self.root = Path(root)
        self.reads = 0
        self._rows: dict[str, tuple[tuple, ScanRow]] = {}
        self._frames: dict[str, dict[str, list[tuple[int, int | None]]]] = {}
        """Scan in hand -> chunk name -> its records' (pose_index, frame): read once, a published chunk never
        changes."""

    def rows(self) -> list[ScanRow]:
        """Every scan under the root: running ones first, then the most recently changed."""
        rows, seen = [], set()
        if not self.root.is_dir():  # not made yet (the daemon makes it at its first scan), or gone: no scans
            self._rows.clear()
            return rows
        with os.scandir(self.root) as entries:
            for entry in entries:
                if entry.name.startswith(".") or not entry.is_dir():
                    continue
                manifest = os.path.join(entry.path, MANIFEST)
                try:
                    st = os.stat(manifest)
                except OSError:
                    continue  # not a capture folder
                seen.add(entry.name)
                row = self._row(entry.name, st)
                row.note = _linked_out(self.root, entry)
                rows.append(row)
        for gone in set(self._rows) - seen:
            del self._rows[gone]
        for gone in set(self._frames) - {r.name for r in rows if r.state in IN_HAND}:
            del self._frames[gone]
        rows.sort(key=lambda r: (r.state not in IN_HAND, -r.mtime, r.name))
        return rows

    def _row(self, name: str, st: os.stat_result) -> ScanRow:
        path = self.root / name
        key: tuple = (st.st_mtime_ns, st.st_size)
        cached = self._rows.get(name)
        if cached and cached[0][:2] == key and cached[1].state not in IN_HAND:
            return cached[1]
        chunks = _chunk_names(path)
        key += (len(chunks), chunks[-1] if chunks else None)
        if cached and cached[0] == key:
            return cached[1]
        row = self._read(name, path, chunks)
        row.mtime = st.st_mtime
        row.published = _published_times(path, chunks[-PACE_POSES:])
        self._rows[name] = (key, row)
        return row

    def _read(self, name: str, path: Path, chunks: list[str]) -> ScanRow:
        self.reads += 1
        try:
            manifest = CaptureReader(path).manifest
            where = str(path / MANIFEST)
            row = ScanRow(name, manifest["state"], planned=_planned(manifest, where),
                          updated_utc=_typed(manifest, "updated_utc", str, where),
                          reason=_typed(manifest, "reason", str, where), chunks=chunks,
                          started_utc=_typed(manifest, "created_utc", str, where),
                          config=_rig_config(manifest, where))
            paused = _typed(manifest, "paused", dict, where)
            frames_per_pose = _typed(manifest, "frames_per_pose", int, where) or 1
            chunk_size = _typed(manifest, "chunk_size", int, where) or 1
        except SpadscanError as exc:
            return ScanRow(name, "error", error=str(exc))
        if paused is not None and row.state == "running":  # the daemon recorded a pause: say so, and why
            row.state, row.reason = "paused", str(paused.get("reason") or "paused")
        if chunks:  # the last pose published is the scan's latest news, later than its manifest's last write
            row.updated_utc = max(filter(None, (row.updated_utc, _published_utc(path / chunks[-1]))))
        if chunks:
            try:
                self.reads += 1
                meta = read_json(path / chunks[-1] / "meta.json").get("measurements") or []
                row.poses = int(meta[-1]["pose_index"]) + 1  # poses are published in order
            # ArithmeticError: int() of an infinite pose_index overflows (a damaged record, not a dead page)
            except (SpadscanError, LookupError, TypeError, ValueError, ArithmeticError) as exc:
                row.error = f"{path / chunks[-1]}: unreadable measurement records ({exc})"
        row.owed = self._owed(name, path, chunks, frames_per_pose, chunk_size) if row.state in IN_HAND else 0
        if row.planned:
            row.progress = min(1.0, row.poses / row.planned)
        return row

    def _owed(self, name: str, path: Path, chunks: list[str], frames_per_pose: int, chunk_size: int) -> int | None:
        """How many poses a scan in hand owes again: those its writer takes again on resuming (protocol's
        `plan_retakes`, as the daemon counts them), its chunks' records read once each. None when a chunk cannot be
        read, or the poses owed cannot be put back in order (the daemon does not resume such a scan)."""
        known = self._frames.setdefault(name, {})
        for gone in set(known) - set(chunks):
            del known[gone]
        for chunk in chunks:
            if chunk in known:
                continue
            try:
                self.reads += 1
                meta = read_json(path / chunk / "meta.json").get("measurements") or []
                known[chunk] = held_frames(meta)
            except (SpadscanError, LookupError, TypeError, ValueError, ArithmeticError):
                return None
        try:
            return len(plan_retakes([(chunk_index(c), known[c]) for c in chunks], frames_per_pose, chunk_size, path))
        except SpadscanError:
            return None


def interrupted(row: ScanRow) -> ScanRow:
    """A scan in hand as it is shown when no daemon holds the root: a copy, since the row is remembered between polls
    and the daemon may come back without the scan's files changing."""
    reason = NO_DAEMON if row.state == "running" else f"{NO_DAEMON}; it was paused: {row.reason}"
    return replace(row, state=INTERRUPTED, reason=reason)


def as_the_daemon_says(row: ScanRow, daemon: dict) -> ScanRow:
    """A scan in hand as the running daemon's own status (`daemon`, its `spadscan ctl status`) says it, a copy: one
    it could not take over (`cannot_take_over`: why, and the way out, in its words), one an earlier daemon also left
    running that it has not taken over (`also_interrupted`), its own scan paused while scan.json still says running
    (a pause that a full disk kept out of scan.json: the daemon's reason). Any other row as it is: scan.json is
    written by that daemon, and the status and the files are read a moment apart."""
    if row.state not in IN_HAND:
        return row
    stuck = daemon.get("cannot_take_over")
    if isinstance(stuck, dict) and stuck.get("scan") == row.name:
        return replace(row, state=NOT_TAKEN_OVER, reason=str(stuck.get("error") or "the daemon cannot take it over"))
    also = daemon.get("also_interrupted")
    if isinstance(also, list) and row.name in also:
        held = daemon.get("scan")
        return replace(row, state=NOT_TAKEN_OVER, reason=(
            f"left running by an earlier daemon; the daemon running now {f'holds {held!r} and ' if held else ''}has "
            f"not taken it over: `spadscan ctl resume {row.name}` takes it over once no scan is held, `spadscan ctl "
            f"abort {row.name}` ends it as aborted, keeping every chunk"))
    if daemon.get("scan") == row.name and daemon.get("state") == "paused" and row.state == "running":
        return replace(row, state="paused", reason=daemon.get("reason") or row.reason)
    return row


def quiet_limit_s(published: list[float]) -> float:
    """How long a running scan may go without news before it is shown as stalled: QUIET_FACTOR times its recent pose
    interval (the median gap between its last PACE_POSES publications: a pause and resume between two poses does not
    stretch it), at least QUIET_FLOOR_S: a healthy pose may take the daemon's whole move timeout (60 s by default: a
    slow arm's long move, the first move of a scan or of a resume, from wherever the arm stood) and then its frames,
    and a silent sensor pauses the scan, recorded, within a few frame timeouts."""
    gaps = [b - a for a, b in zip(published, published[1:])]
    return max(QUIET_FLOOR_S, QUIET_FACTOR * statistics.median(gaps)) if gaps else QUIET_FLOOR_S


def stalled(row: ScanRow, now: float) -> ScanRow:
    """A running scan as it is shown at `now` (unix seconds): stalled, a copy, when its latest news (its newest
    published pose or its scan.json's last write, whichever is later: a resume rewrites scan.json) is older than
    `quiet_limit_s`; any other row as it is. A copy, since the row is remembered between polls."""
    if row.state != "running":
        return row
    quiet = now - max([row.mtime, *row.published[-1:]])
    if quiet <= quiet_limit_s(row.published):
        return row
    reason = f"no new pose for {ago(quiet)}: the daemon may be paused or stuck; `spadscan ctl status` says why"
    return replace(row, state=STALLED, reason=reason, quiet_s=round(quiet, 1))


def ago(seconds: float) -> str:
    """A time span as the page writes one (its `ago`)."""
    if seconds < 90:
        return f"{round(seconds)} s"
    if seconds < 90 * 60:
        return f"{round(seconds / 60)} min"
    return f"{seconds / 3600:.1f} h"


LINKED_OUT = ("its folder links outside the captures root: the dashboard serves nothing there, so its files have "
              "no links")


def _linked_out(root: Path, entry: os.DirEntry) -> str | None:
    """A row note for a scan folder that is a link the server does not follow (safe_path: nothing outside the root).
    The scan is still listed, with its progress and its reconstructions summed up: the links alone are left out
    (results.py), and the note says why. Only links are resolved: a poll costs no more for the other scans."""
    if not entry.is_symlink() or safe_path(root, url_path(entry.name, MANIFEST)):
        return None
    return LINKED_OUT


def _published_utc(chunk: Path) -> str | None:
    """When a chunk was published (its folder's modification time: the rename that published it), as the manifest
    writes times (ISO 8601 UTC with milliseconds); None when it cannot be read."""
    try:
        mtime = chunk.stat().st_mtime
    except OSError:
        return None
    return _dt.datetime.fromtimestamp(mtime, _dt.timezone.utc).isoformat(timespec="milliseconds")


def _published_times(path: Path, chunks: list[str]) -> list[float]:
    """When each of `chunks` was published (its folder's modification time), oldest first; one that cannot be read
    (removed meanwhile) is left out."""
    times = []
    for name in chunks:
        try:
            times.append((path / name).stat().st_mtime)
        except OSError:
            continue
    return sorted(times)


def _chunk_names(path: Path) -> list[str]:
    try:
        return sorted(e.name for e in os.scandir(path) if chunk_index(e.name) is not None and e.is_dir())
    except OSError:
        return []


def scan_detail(root: Path, row: ScanRow) -> dict:
    """What the dashboard shows of the scan in hand (or the last one): its row, frame rate over its last frames while
    it runs, and its last histograms (zones, at most MAX_PLOT_BINS bins, with the distance of the first bin and the
    bin width in metres)."""
    detail = row.to_dict()
    if row.error or not row.chunks:
        return detail
    try:
        reader = CaptureReader(Path(root) / row.name)
        frames = []
        for name in reversed(row.chunks):
            chunk = reader.read_chunk(name)
            if not frames:
                detail["histograms"] = plot_histograms(chunk.hists[-1], reader.sensor)
            frames = list(chunk.meta) + frames
            if len(frames) >= RATE_FRAMES:
                break
    except SpadscanError as exc:
        detail["error"] = str(exc)
        return detail
    if row.state == "running":  # a paused, interrupted, stalled, complete or aborted scan takes no frames: no rate
        detail.update(frame_rates(frames[-RATE_FRAMES:]))
        detail["eta_s"] = time_left_s(row.poses, row.planned, detail["poses_per_min"], row.owed or 0)
    return detail


def time_left_s(poses: int, planned: int | None, poses_per_min: float | None, owed: int = 0) -> float | None:
    """Seconds until a running scan has taken every pose left at its recent pace (poses per minute over its last
    frames), from its last published pose: the poses planned past it and the `owed` ones it takes again, as the
    daemon counts them (`ctl status`'s eta_s); None when the plan or the pace is unknown."""
    if not planned or not poses_per_min or not math.isfinite(poses_per_min) or poses_per_min <= 0:
        return None
    return round(60.0 * (max(0, planned - poses) + max(0, owed)) / poses_per_min, 1)


def frame_rates(meta: list[dict]) -> dict:
    """Frames per second and poses per minute over measurement records in order (their t_end, seconds), since the
    last stop among them (`_since_last_stop`). A record without a finite t_end (damaged: a NaN would make both rates
    NaN) counts for neither."""
    meta = _since_last_stop([m for m in meta if _finite(m.get("t_end"))])
    times = [float(m["t_end"]) for m in meta]
    if len(times) < 2 or times[-1] <= times[0]:
        return {"frames_per_s": None, "poses_per_min": None}
    span = times[-1] - times[0]
    poses = len({m.get("pose_index") for m in meta})
    return {"frames_per_s": (len(times) - 1) / span, "poses_per_min": 60.0 * max(0, poses - 1) / span}


def _since_last_stop(meta: list[dict]) -> list[dict]:
    """The records from the first pose after the last stop among them: a move between two poses over STOP_FACTOR times
    the median one (a pause, a daemon restarted). Measured across it, the pace of a resumed scan read 0.41 frames/s
    and 4 minutes left where it ran at 4.8 and had 20 s to go."""
    starts: dict = {}
    for m in meta:
        starts.setdefault(m.get("pose_index"), float(m["t_end"]))
    times = sorted(starts.values())
    moves = np.diff(times)
    if len(moves) < 3:
        return meta
    stops = np.flatnonzero(moves > STOP_FACTOR * float(np.median(moves)))
    if not stops.size:
        return meta
    resumed = times[int(stops[-1]) + 1]
    return [m for m in meta if float(m["t_end"]) >= resumed]


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def plot_histograms(hist: np.ndarray, sensor) -> dict:
    """A (zones, bins) histogram max-pooled to at most MAX_PLOT_BINS bins, for the page's small plot. The bins before
    zero distance (a sensor's zero bin lies inside its histogram) are left out: the plot's axis starts at 0 m."""
    hist = np.asarray(hist, dtype=np.float64)
    first = _first_bin_at_zero(sensor, hist.shape[1])
    hist = hist[:, first:]
    pool = int(np.ceil(hist.shape[1] / MAX_PLOT_BINS))
    bins = hist.shape[1] // pool * pool
    pooled = hist[:, :bins].reshape(hist.shape[0], -1, pool).max(axis=2) if pool > 1 else hist
    width = float(sensor.bin_width_m) * pool
    # the axis labels bin centres: pooled bin k covers bin coordinates first + [k * pool, (k + 1) * pool) (bin i
    # covers [i, i + 1) in the sensor model), so its centre is at coordinate first + k * pool + pool / 2
    return {"counts": pooled.round(1).tolist(), "first_m": float(sensor.range_of_bin(first + pool / 2)),
            "bin_m": width, "zones": int(hist.shape[0])}


def _first_bin_at_zero(sensor, n_bins: int) -> int:
    """The first bin whose start is at zero distance or beyond (0 when every bin is; none past the last bin)."""
    ahead = np.asarray(sensor.range_of_bin(np.arange(n_bins))) >= 0.0
    return int(np.argmax(ahead)) if ahead.any() else 0
