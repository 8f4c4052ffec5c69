"""Adaptive scans: which pose comes next, chosen from the live reconstruction's ranking or the fallback plan.

An adaptive scan's plan (`scan_plan.build_plan`) is a Fibonacci plan of `views` poses whose first `initial_views`
are a well-spread subset; its rows from the pose being chosen onwards are the *fallback queue*. Before each later
pose, `ViewChooser.choose` reads `<capture>/next_views.json` (`protocol.next_views`) and takes the best candidate
that scores above 0 (a view that sees nothing scores 0: a ranking of zeros tells nothing), is fresh (ranked fewer
than `next_views_max_lag` poses ago and within `next_views_max_age_s`), lies at least `min_view_spacing_deg` from
every pose taken, and passes the workspace checks (`workspace.py`: the pose and the straight move from the pose
before). That candidate replaces the queued pose nearest to it, so the scan still ends at `views` poses. Otherwise
(no file, a stale or malformed one, nothing that passes) the next queued pose is taken (the first not within the
spacing of a taken pose, where one is). The daemon never waits for a worker: reading the file is all the choice
costs.

The plan's rows before the pose being chosen are the poses taken, so `schedule.npy`, rewritten before each chosen
pose is published, keeps meaning "row i is pose i" and a resumed scan reads its fallback queue back from it. Each
measurement records why its pose was taken (`view_choice` in its meta, its `why`: `initial`, `adaptive` or `fallback`
as chosen here, or `retaken`, which the daemon writes for a pose taken again after its chunk was moved out of the
capture, at the pose it had).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spadscan.protocol.errors import CaptureError, ConfigError
from spadscan.protocol.live_status import read_status, status_path
from spadscan.protocol.next_views import (FILE, NextViews, candidate_poses, read_next_views, too_close,
                                          view_angles_deg)

from .config import ArmConfig, ScanConfig, scan_to_dict
from .scan_plan import tcp_from_sensor
from .workspace import check_workspace

log = logging.getLogger("spadscan.daemon")


@dataclass
class Choice:
    """Pose i's sensor pose (4, 4) and why it was taken: `record` goes into its measurements' meta."""

    pose: np.ndarray
    record: dict
    candidate: int | None = None
    """Index of the candidate taken (adaptive), else None."""

    @property
    def why(self) -> str:
        return self.record["why"]


@dataclass
class ViewChooser:
    """Chooses the poses of one adaptive scan. All methods are plain computation and file reads (run them in a
    thread); `choose` never changes the plan it is given."""

    scan: ScanConfig
    arm: ArmConfig
    hand_eye: np.ndarray
    capture: Path
    candidates: np.ndarray = field(init=False)
    """(N, 4, 4) the candidate sensor poses (`protocol.next_views.candidate_poses`)."""
    refused: set = field(default_factory=set)
    """Candidates the arm's controller refused (never offered again)."""
    _placeable: np.ndarray = field(init=False)
    _last_problem: str | None = None

    def __post_init__(self):
        self.candidates = candidate_poses(scan_to_dict(self.scan))
        tcp = tcp_from_sensor(self.candidates, self.hand_eye)
        self._placeable = np.array([_pose_ok(t, self.arm) for t in tcp], dtype=bool)

    @property
    def target(self) -> np.ndarray:
        return np.asarray(self.scan.target, dtype=np.float64)

    def choose(self, plan: np.ndarray, i: int, now=None) -> tuple[Choice, np.ndarray]:
        """Pose i of the plan (P, 4, 4): its rows before i are the poses taken, from i on the fallback queue.
        Returns the choice and the plan with row i set to it (a new array; the queue keeps its order, less the pose
        an adaptive choice replaces). Raises ConfigError when no pose left can be reached from pose i - 1."""
        n0 = self.scan.initial_views
        if i < n0:
            return Choice(plan[i], {"why": "initial", "detail": f"well-spread initial view {i + 1} of {n0}"}), plan
        taken = plan[:i]
        nv, stale = self._ranking(i, now)
        if nv is not None:
            k, problem = self._best(nv, taken, plan[i - 1] if i else None)
            if k is not None:
                j = self._candidate_index(nv.poses[k])
                record = {"why": "adaptive", "rank": int(k), "score": float(nv.scores[k]),
                          "ranked_at_poses": int(nv.pose_count), "ranked_utc": nv.created_utc,
                          "measure": nv.measure}
                return Choice(nv.poses[k], record, j), _replace_nearest(plan, i, nv.poses[k], self.target)
            stale = problem
        return self.fallback(plan, i, stale)

    def refuse(self, candidate: int | None) -> None:
        """The arm's controller refused this candidate: it is never offered again."""
        if candidate is not None:
            self.refused.add(int(candidate))

    # ---- the ranking ---------------------------------------------------------------------------------------------
    def _ranking(self, i: int, now) -> tuple[NextViews | None, str]:
        """(the ranking, None) when a fresh one is there, else (None, why not)."""
        try:
            nv = read_next_views(self.capture)
        except CaptureError as exc:
            if not (self.capture / FILE).exists():
                if not status_path(self.capture).exists():
                    # Said once: a scan no live worker follows is its fallback plan throughout. One that a live job
                    # follows but has not ranked yet (its first fit takes a while) is the usual start: not said.
                    self._note(f"scan {self.capture.name}: no live reconstruction follows it (no {FILE}, no live "
                               f"status): taking the fallback plan until one ranks its views (is a worker running "
                               f"with --live?)")
                return None, f"no {FILE} yet"
            self._note(f"scan {self.capture.name}: {exc}; taking the fallback plan")
            return None, f"{FILE} unreadable ({exc})"
        lag = i - nv.pose_count
        if lag < 0:
            return None, f"{FILE} ranked at {nv.pose_count} poses, more than the {i} taken"
        if lag >= self.scan.next_views_max_lag:  # at least 2 (config.check_scan): pose i is chosen during i - 1
            return None, (f"{FILE} stale: ranked at {nv.pose_count} poses, {lag} before this one "
                          f"(next_views_max_lag {self.scan.next_views_max_lag})")
        age = nv.age_s(now)
        if abs(age) > self.scan.next_views_max_age_s:
            return None, (f"{FILE} stale: ranked {age:.0f} s ago (next_views_max_age_s "
                          f"{self.scan.next_views_max_age_s:g})")
        return nv, ""

    def _best(self, nv: NextViews, taken: np.ndarray, prev_sensor: np.ndarray | None) -> tuple[int | None, str]:
        """The best-ranked candidate that passes every check, or (None, why none does)."""
        if not np.any(nv.scores > 0):
            return None, f"no ranked view scores above 0 (all {len(nv.poses)} score 0 or less: nothing to gain)"
        close = too_close(nv.poses, taken, self.target, self.scan.min_view_spacing_deg)
        prev = None if prev_sensor is None else tcp_from_sensor(prev_sensor, self.hand_eye)
        counts = {"scoring 0 or less": 0, "too close to a pose taken": 0, "outside the workspace": 0,
                  "refused by the controller": 0}
        for k in range(len(nv.poses)):
            # A view that sees nothing scores 0: the order among such views is the candidates' spiral order, not a
            # ranking, and following it would pile poses into the spiral's first band instead of the planned ones.
            if not nv.scores[k] > 0:
                counts["scoring 0 or less"] += 1
                continue
            if close[k]:
                counts["too close to a pose taken"] += 1
                continue
            j = self._candidate_index(nv.poses[k])
            if j is not None and j in self.refused:
                counts["refused by the controller"] += 1
                continue
            if not self._reachable(nv.poses[k], j, prev):
                counts["outside the workspace"] += 1
                continue
            return k, ""
        detail = ", ".join(f"{v} {what}" for what, v in counts.items() if v)
        return None, f"none of the {len(nv.poses)} ranked views passes ({detail})"

    def _reachable(self, sensor_pose: np.ndarray, j: int | None, prev_tcp: np.ndarray | None) -> bool:
        if j is not None and not self._placeable[j]:
            return False
        tcp = tcp_from_sensor(sensor_pose, self.hand_eye)
        try:
            check_workspace(tcp[None], self.arm, "candidate", prev_tcp)
        except ConfigError:
            return False
        return True

    def _candidate_index(self, pose: np.ndarray) -> int | None:
        """Which of the candidates this pose is (within 0.1 mm), or None: a ranking may offer other poses too."""
        d = np.linalg.norm(self.candidates[:, :3, 3] - pose[:3, 3], axis=1)
        j = int(np.argmin(d))
        return j if d[j] < 1e-4 else None

    # ---- the fallback plan ---------------------------------------------------------------------------------------
    def fallback(self, plan: np.ndarray, i: int, why: str) -> tuple[Choice, np.ndarray]:
        """The first queued pose not within the spacing of a taken pose (else the first queued) whose straight move
        from pose i - 1 passes the workspace checks."""
        queue = plan[i:]
        close = too_close(queue, plan[:i], self.target, self.scan.min_view_spacing_deg)
        prev = tcp_from_sensor(plan[i - 1], self.hand_eye) if i else None
        for q in [*np.flatnonzero(~close), *np.flatnonzero(close)]:
            if prev is not None:
                try:
                    check_workspace(tcp_from_sensor(queue[q], self.hand_eye)[None], self.arm, "fallback", prev)
                except ConfigError:
                    continue
            rows = plan.copy()
            rows[i:] = np.concatenate([queue[q:q + 1], queue[:q], queue[q + 1:]])
            return Choice(queue[q], {"why": "fallback", "detail": why or "fallback plan"}), rows
        raise ConfigError(f"no pose left in the plan can be reached by a straight move from pose {i - 1} "
                          f"([arm] limits)")

    def _note(self, line: str) -> None:
        """Log a problem with the ranking once, not at every pose."""
        if line != self._last_problem:
            log.warning("%s", line)
            self._last_problem = line


def _replace_nearest(plan: np.ndarray, i: int, pose: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The plan with `pose` at row i and the queued pose nearest to it (by angle from the target) left out."""
    queue = plan[i:]
    drop = int(np.argmin(view_angles_deg(pose[None], queue, target)[0]))
    rows = plan.copy()
    rows[i] = pose
    rows[i + 1:] = np.concatenate([queue[:drop], queue[drop + 1:]])
    return rows


def _pose_ok(tcp: np.ndarray, arm: ArmConfig) -> bool:
    try:
        check_workspace(tcp[None], arm, "candidate")
    except ConfigError:
        return False
    return True


def live_converged(capture: Path, min_views: int) -> str | None:
    """Why the scan may end now: the live reconstruction's recon/live/status.json (`protocol.live_status`) says it
    is following the scan (state 'live') and converged with at least min_views views used; else None (also for a
    missing or malformed file: a worker's file never stops a scan by being broken)."""
    try:
        status = read_status(status_path(capture))
    except CaptureError:
        return None
    # Only a fit following the scan now: a 'queued', 'stopped' or 'aborted' status keeps its last figures, and a
    # converged flag there is a stopped job's, not the scan's.
    if status.state != "live" or not status.converged or status.views_used < min_views:
        return None
    return f"the live reconstruction converged with {status.views_used} views"


__all__ = ["ViewChooser", "Choice", "live_converged"]
