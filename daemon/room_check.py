"""Whether the captures' disk can take a scan's next pose, found by writing that pose's files for real."""

from __future__ import annotations

import os
import shutil

from spadscan.protocol.atomic_files import write_durable
from spadscan.protocol.capture_format import TMP_PREFIX
from spadscan.protocol.disk_full import FULL_ERRNOS

from .describe import describe, write_advice
from .scan_job import ScanJob

ROOM_PROBE = f"{TMP_PREFIX}room-check"  # the hidden folder a resume writes a pose's worth of files into (`no_room`)
META_BYTES = 4096  # what a frame's record in a chunk's meta.json may take, at most (depths, confidences, extra)


def no_room(job: ScanJob, model) -> str | None:
    """Why the captures' disk cannot take the next pose's chunk, with what to do; None when it can. Its files are
    written for real, at the sizes they will have (`chunk_sizes`), in a hidden folder of the scan's (ROOM_PROBE,
    removed after; a writer reopening the capture drops it too): a free-space figure would miss quotas and the
    filesystem's own overheads. Random bytes: a compressing filesystem stores them whole, as it does counts."""
    probe = path = job.path / ROOM_PROBE
    try:
        probe.mkdir(exist_ok=True)
        for name, size in chunk_sizes(job.scan.frames_per_pose, model):
            path = probe / name
            write_durable(path, os.urandom(size))
    except OSError as exc:
        if exc.errno in FULL_ERRNOS:
            return (f"the captures' disk is still full ({exc.strerror}: no room for the next pose's chunk in "
                    f"{job.path}); make room on it, then `spadscan ctl resume`")
        named = exc if exc.filename else OSError(exc.errno, exc.strerror or str(exc), str(path))  # (a write's has none)
        return f"{describe(named, 'checking for room for the next pose')}; {write_advice(named)}"
    finally:
        shutil.rmtree(probe, ignore_errors=True)
    return None


def chunk_sizes(frames: int, model) -> list[tuple[str, int]]:
    """The files of a chunk of `frames` frames of sensor `model` and the bytes each takes at most: counts and
    reference counts as uint32, poses as 4x4 float64, each behind a 128-byte .npy header; META_BYTES a frame's
    record in meta.json."""
    return [("hists.npy", 128 + frames * model.n_zones * model.n_bins * 4),
            ("poses.npy", 128 + frames * 16 * 8),
            ("reference.npy", 128 + frames * model.n_bins * 4),
            ("meta.json", frames * META_BYTES)]
