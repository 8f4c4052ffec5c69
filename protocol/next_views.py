"""Next-best-view candidates: the file `<capture>/next_views.json` a live reconstruction writes and the daemon reads,
and the candidate poses both sides agree on.

An adaptive scan (`schedule = "adaptive"`) considers a fixed set of candidate sensor poses: a dense Fibonacci spiral
over the scan's elevation band at its radius, every view looking at the target (`candidate_poses`, from the scan's
settings as the manifest's `schedule` record holds them). The live reconstruction ranks them by how much each would
tell it and writes the ranking; the daemon takes the best candidate that passes its own checks and is not within
`min_view_spacing_deg` of a pose already taken, nor a view already taken whatever that spacing (`too_close`).

The file (JSON, UTF-8, replaced atomically: written to a hidden file of the writer's own, fsynced, renamed):

    {"format": "spadscan-next-views", "version": 1,
     "pose_count": 40,                    poses published in the capture when the ranking was made
     "created_utc": "2026-11-26T14:15:52.975+00:00",
     "measure": "coverage",               how the scores were made (informative)
     "candidates": [{"pose": [[4 x 4]], "score": 0.83}, ...]}   best first; pose: sensor-to-world, metres

Scores are finite numbers, higher = more useful, comparable only within one file. A reader refuses anything else in
one line (`read_next_views`): the daemon then takes its fallback plan's next pose.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic_files import write_atomic
from .capture_format import POSE_TOL, one_line
from .errors import CaptureError
from .iso_time import utc_now
from .schedules import fibonacci_hemisphere

FILE = "next_views.json"
FORMAT = "spadscan-next-views"
VERSION = 1
MAX_CANDIDATES = 100_000
"""The most candidates a file may hold (a bound on what a reader parses)."""
CANDIDATES = 512
"""Candidate poses of an adaptive scan by default: about 5.5 degrees apart over the default 10-80 degree band."""


@dataclass
class NextViews:
    """A ranking of candidate views. poses (N, 4, 4) float64 sensor-to-world (metres), best first; scores (N,);
    pose_count: poses published when it was made; created_utc: ISO 8601 UTC; measure: how it was scored."""

    poses: np.ndarray
    scores: np.ndarray
    pose_count: int
    created_utc: str
    measure: str = ""

    def age_s(self, now: _dt.datetime | None = None) -> float:
        """Seconds since the ranking was made (negative when its clock runs ahead of ours)."""
        now = now or _dt.datetime.now(_dt.timezone.utc)
        return (now - _parse_time(self.created_utc, "created_utc")).total_seconds()


def ranked(poses: np.ndarray, scores: np.ndarray, pose_count: int, measure: str = "",
           created_utc: str | None = None) -> NextViews:
    """A NextViews of candidate poses (N, 4, 4) and their scores (N,), sorted best first (stable for ties)."""
    poses = np.asarray(poses, dtype=np.float64)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(scores):
        raise CaptureError(f"next views: poses {poses.shape} and scores {scores.shape} must be (N, 4, 4) and (N,)")
    order = np.argsort(-scores, kind="stable")
    nv = NextViews(poses[order], scores[order], int(pose_count), created_utc or utc_now(), str(measure))
    _check(nv, "next views")
    return nv


def write_next_views(capture, nv: NextViews) -> Path:
    """Replace `<capture>/next_views.json` atomically (temp file, fsync, rename, fsync the folder); returns its path.

    The temporary file is this writer's own (`write_atomic`), not one of the capture writer's `.tmp-` names: the
    daemon drops those whenever it reopens the scan, and this file is written by the worker while the scan runs."""
    path = Path(capture) / FILE
    _check(nv, str(path))
    data = {"format": FORMAT, "version": VERSION, "pose_count": int(nv.pose_count), "created_utc": nv.created_utc,
            "measure": nv.measure,
            "candidates": [{"pose": p.tolist(), "score": float(s)} for p, s in zip(nv.poses, nv.scores)]}
    write_atomic(path, json.dumps(data, indent=1) + "\n")
    return path


def read_next_views(capture) -> NextViews:
    """Read and check `<capture>/next_views.json`; every problem (missing, truncated, a bad pose or score, a newer
    version) is one CaptureError line naming the file."""
    path = Path(capture) / FILE
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CaptureError(f"{path}: missing") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise CaptureError(f"{path}: unreadable JSON ({one_line(exc)})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CaptureError(f"{path}: not a next-views file (format {_get(data, 'format')!r}, expected {FORMAT!r})")
    version = data.get("version")
    if not (_is_int(version) and 1 <= version <= VERSION):
        raise CaptureError(f"{path}: version {version!r} is not one this reader knows (1..{VERSION})")
    count = data.get("pose_count")
    if not (_is_int(count) and count >= 0):
        raise CaptureError(f"{path}: pose_count {count!r} must be an integer >= 0")
    created = data.get("created_utc")
    _parse_time(created, f"{path}: created_utc")
    measure = data.get("measure", "")
    if not isinstance(measure, str):
        raise CaptureError(f"{path}: measure {measure!r} must be a string")
    cands = data.get("candidates")
    if not isinstance(cands, list) or not 1 <= len(cands) <= MAX_CANDIDATES:
        raise CaptureError(f"{path}: candidates must be a list of 1..{MAX_CANDIDATES} objects")
    poses, scores = np.empty((len(cands), 4, 4)), np.empty(len(cands))
    for k, c in enumerate(cands):
        if not isinstance(c, dict) or "pose" not in c or "score" not in c:
            raise CaptureError(f"{path}: candidate {k} must be an object with 'pose' and 'score'")
        try:
            poses[k] = np.asarray(c["pose"], dtype=np.float64)
        except (TypeError, ValueError):
            raise CaptureError(f"{path}: candidate {k}: pose must be a 4x4 array of numbers (metres)") from None
        score = c["score"]
        if isinstance(score, bool) or not isinstance(score, (int, float)) or not math.isfinite(score):
            raise CaptureError(f"{path}: candidate {k}: score {score!r} must be a finite number")
        scores[k] = score
    nv = NextViews(poses, scores, count, created, measure)
    _check(nv, str(path))
    return nv


# ---- candidates -------------------------------------------------------------------------------------------------------
def candidate_poses(schedule: dict, n: int | None = None) -> np.ndarray:
    """The candidate sensor poses (n, 4, 4) of an adaptive scan: a Fibonacci spiral of n views (default: the record's
    `candidates`, else CANDIDATES) over the band min_elevation_deg..max_elevation_deg at radius_m around target,
    each looking at the target. `schedule`: the scan's settings as the manifest's `schedule` record holds them."""
    try:
        n = int(schedule.get("candidates", CANDIDATES) if n is None else n)
        return fibonacci_hemisphere(n, float(schedule["radius_m"]), schedule.get("target", (0.0, 0.0, 0.0)),
                                    float(schedule["min_elevation_deg"]), float(schedule["max_elevation_deg"]))
    except KeyError as exc:
        raise CaptureError(f"scan schedule record lacks {exc.args[0]!r}: cannot place the candidate views") from None
    except (TypeError, ValueError) as exc:
        raise CaptureError(f"scan schedule record: {one_line(exc)}") from None


def view_angles_deg(a: np.ndarray, b: np.ndarray, target) -> np.ndarray:
    """Angles (degrees) between the directions from `target` to the sensor positions of poses a (n, 4, 4) and
    b (m, 4, 4): (n, m). Two views this close look at the target from nearly the same side."""
    t = np.asarray(target, dtype=np.float64).reshape(3)
    da = _unit(np.asarray(a, dtype=np.float64)[:, :3, 3] - t)
    db = _unit(np.asarray(b, dtype=np.float64)[:, :3, 3] - t)
    return np.degrees(np.arccos(np.clip(da @ db.T, -1.0, 1.0)))


SAME_VIEW_DEG = 0.01
"""Two views this close (degrees, seen from the target) are the same view: `too_close` holds them apart whatever the
spacing asked for, so that a spacing of 0 never lets a scan take one ranked view over and over."""


def too_close(candidates: np.ndarray, taken: np.ndarray, target, min_spacing_deg: float) -> np.ndarray:
    """(n,) bool: candidate poses (n, 4, 4) within min_spacing_deg (at least SAME_VIEW_DEG) of any taken pose
    (m, 4, 4), seen from target."""
    candidates = np.asarray(candidates, dtype=np.float64).reshape(-1, 4, 4)
    taken = np.asarray(taken, dtype=np.float64).reshape(-1, 4, 4)
    if len(taken) == 0:
        return np.zeros(len(candidates), dtype=bool)
    return view_angles_deg(candidates, taken, target).min(axis=1) < max(min_spacing_deg, SAME_VIEW_DEG)


# ---- checks ---------------------------------------------------------------------------------------------------------
def _check(nv: NextViews, where: str) -> None:
    p = nv.poses
    if p.ndim != 3 or p.shape[1:] != (4, 4) or len(p) == 0 or len(p) > MAX_CANDIDATES:
        raise CaptureError(f"{where}: candidates must be 1..{MAX_CANDIDATES} poses of shape (4, 4), got {p.shape}")
    if nv.scores.shape != (len(p),) or not np.all(np.isfinite(nv.scores)):
        raise CaptureError(f"{where}: every candidate needs one finite score")
    if not np.all(np.isfinite(p)):
        k = int(np.flatnonzero(~np.isfinite(p).all(axis=(1, 2)))[0])
        raise CaptureError(f"{where}: candidate {k}: pose holds non-finite values")
    r = p[:, :3, :3]
    err = np.abs(r @ r.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    last_row = np.abs(p[:, 3] - [0, 0, 0, 1]).max(axis=1)
    bad = (err > POSE_TOL) | (np.abs(np.linalg.det(r) - 1) > POSE_TOL) | (last_row > POSE_TOL)
    if bad.any():
        raise CaptureError(f"{where}: candidate {int(np.flatnonzero(bad)[0])}: pose is not a rigid transform")
    if not (_is_int(nv.pose_count) and nv.pose_count >= 0):
        raise CaptureError(f"{where}: pose_count {nv.pose_count!r} must be an integer >= 0")
    _parse_time(nv.created_utc, f"{where}: created_utc")


def _parse_time(text, where: str) -> _dt.datetime:
    try:
        t = _dt.datetime.fromisoformat(text)
    except (TypeError, ValueError):
        raise CaptureError(f"{where} {text!r} must be an ISO 8601 time with its UTC offset") from None
    if t.tzinfo is None:
        raise CaptureError(f"{where} {text!r} lacks its UTC offset (+00:00)")
    return t


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _get(data, key):
    return data.get(key) if isinstance(data, dict) else None


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


__all__ = ["FILE", "NextViews", "ranked", "write_next_views", "read_next_views", "candidate_poses",
           "view_angles_deg", "too_close", "CANDIDATES", "SAME_VIEW_DEG"]
