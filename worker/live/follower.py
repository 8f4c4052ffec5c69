"""Following a scan while it is written: each poll re-reads the manifest and reads the chunks published since the
last one (a chunk appears whole, by one rename, and never changes: see docs/capture_format.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spadscan.protocol.capture_reader import CaptureReader


@dataclass
class ScanProgress:
    """What a poll found. `state`: the manifest's ('running', 'complete' or 'aborted')."""

    state: str
    reason: str | None
    views_published: int
    """Poses with at least one published measurement."""
    views_planned: int | None
    new_chunks: int
    """Chunks read by this poll."""
    manifest: dict = field(default_factory=dict)
    poses: np.ndarray | None = field(default=None, compare=False, repr=False)
    """(views_published, 4, 4) sensor poses of the published views, in pose-index order (None: not known)."""

    @property
    def ended(self) -> bool:
        """The scan will publish nothing more (complete or aborted)."""
        return self.state != "running"


class ScanFollower:
    """Reads a capture's chunks as they land. Raises CaptureError (one line) for a malformed manifest or chunk."""

    def __init__(self, capture: Path):
        self.capture = Path(capture)
        self.reader = CaptureReader(self.capture)
        self._seen: set[str] = set()
        self._poses: dict[int, np.ndarray] = {}
        """Each published pose index's sensor pose (its first measurement's, as the reconstruction takes it)."""

    def poll(self) -> ScanProgress:
        """Re-read the manifest, then read every chunk published since the last poll. The manifest is read first: a
        scan that says it has ended has published every chunk before saying so, so the chunks listed after it are
        all there are."""
        state = self.reader.refresh()
        new = [name for name in self.reader.chunk_names() if name not in self._seen]
        for name in new:
            chunk = self.reader.read_chunk(name)
            for meta, pose in zip(chunk.meta, chunk.poses):
                self._poses.setdefault(int(meta["pose_index"]), pose)
            self._seen.add(name)
        manifest = self.reader.manifest
        planned = manifest.get("planned_poses")
        poses = np.stack([self._poses[k] for k in sorted(self._poses)]) if self._poses else np.zeros((0, 4, 4))
        return ScanProgress(state=state, reason=manifest.get("reason"), views_published=len(self._poses),
                            views_planned=planned if isinstance(planned, int) and not isinstance(planned, bool)
                            else None, new_chunks=len(new), manifest=manifest, poses=poses)


__all__ = ["ScanFollower", "ScanProgress"]
