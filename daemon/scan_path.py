"""A scan's path through the workspace: the poses it has left and a retake's way back along it, checked against the
[arm] limits; whether the arm stands on that path."""

from __future__ import annotations

import numpy as np

from spadscan.protocol.errors import ConfigError

from .scan_job import ScanJob
from .workspace import check_workspace

ON_PATH_M = 0.01  # an arm this close to a straight move between two poses of a scan's path stands on that path


def check_left(job: ScanJob, arm) -> None:
    """Check the poses a scan has left against the workspace: as a path for a planned scan; pose by pose for an
    adaptive one, whose moves are checked as each pose is chosen (the row being taken when it stopped may be a
    ranked view that the rest of the plan was never meant to follow)."""
    retakes = job.writer.retakes if job.writer is not None else []
    first = min([job.next_pose, *(r.pose for r in retakes)])  # poses owed again are reached back along the path
    left, where = job.tcp_poses[first:], f"scan {job.name!r}"
    if job.scan.schedule != "adaptive":
        check_workspace(left, arm, where, first=first)
        return
    for k, tcp in enumerate(left):
        check_workspace(tcp[None], arm, f"{where} pose {first + k}")


def check_way(job: ScanJob, first: int, last: int, arm) -> None:
    """Check the retake's way, the scan's path from pose `first` to pose `last` (walked back and forth along it),
    against the workspace: a ConfigError names the pose or move the current [arm] limits refuse (the arm not moved)."""
    try:
        check_workspace(job.tcp_poses[first:last + 1], arm, f"scan {job.name!r}", first=first, of=job.n_poses)
    except ConfigError as exc:
        raise ConfigError(f"{exc}; the arm is not moved (before pose {last + 1} it walks the scan's path from pose "
                          f"{first} to pose {last}: a straight move across the scan would cross the object): restore "
                          f"the [arm] limits the scan was planned with and restart the daemon, or `spadscan ctl "
                          f"abort`") from None


def back_on_path(job: ScanJob, here: np.ndarray) -> bool:
    """Whether TCP position `here` (m) lies on the scan's path before its last published pose (within ON_PATH_M of
    a straight move between two published poses), and not on the move from that pose to the next one (where any
    stop of a scan going on leaves the arm): only a stop on the retake's way forward leaves it there."""
    last = job.next_pose - 1
    path = job.tcp_poses[:last + 1, :3, 3]
    if len(path) < 2 or segment_distance(path[:-1], path[1:], here).min() > ON_PATH_M:
        return False
    on = job.tcp_poses[last:last + 2, :3, 3]
    if len(on) < 2:  # no pose follows the last published one
        return True
    return float(segment_distance(on[:1], on[1:], here)[0]) > ON_PATH_M


def segment_distance(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Distances (m) from point p (3,) to the segments a[k] -> b[k] ((n, 3) each)."""
    ab = b - a
    length2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18)
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / length2, 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * ab - p, axis=1)
