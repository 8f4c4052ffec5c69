"""A writer reopened with an earlier writer's book of chunks (`CaptureWriter.resume(path, known=book)`) reads again
only the chunks whose files changed since, and counts, plans retakes and refuses exactly as a resume that reads
every chunk: a chunk moved out, moved back, damaged or added is noticed."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_writer import CaptureWriter, Retake
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.sensor_presets import sensor_preset

SENSOR = sensor_preset("tmf8820")


def frame(pose: int, k: int) -> Measurement:
    hist = np.full((SENSOR.n_zones, SENSOR.n_bins), 10 * pose + k + 1)
    return Measurement(hist, np.eye(4), pose, k, np.ones(SENSOR.n_bins), {})


def capture(tmp_path, poses: int, frames: int = 2, name: str = "scan") -> CaptureWriter:
    """A capture of `poses` poses x `frames` frames, one chunk a pose (as the daemon flushes); its writer."""
    w = CaptureWriter.create(tmp_path / name, SENSOR, planned_poses=np.stack([np.eye(4)] * 20), chunk_size=64,
                             frames_per_pose=frames)
    for i in range(poses):
        for k in range(frames):
            w.append(frame(i, k))
        w.flush()
    return w


def progress(w: CaptureWriter) -> tuple:
    return w.n_published, w.next_pose_index, w.retakes, w._next_chunk


def test_chunks_a_writer_published_are_not_read_again(tmp_path, reads):
    w = capture(tmp_path, poses=6)
    again = CaptureWriter.resume(w.path, known=w.book)
    assert reads == []
    assert progress(again) == (12, 6, [], 6)
    for k in range(2):
        again.append(frame(6, k))
    again.flush()
    third = CaptureWriter.resume(w.path, known=again.book)  # what the second writer published is in its book
    assert reads == [] and progress(third) == (14, 7, [], 7)
    assert progress(CaptureWriter.resume(w.path)) == progress(third)  # the same as a resume reading them all
    assert len(reads) == 7


def test_chunks_read_whole_once_are_not_read_again(tmp_path, reads):
    w = capture(tmp_path, poses=4)
    first = CaptureWriter.resume(w.path)
    assert len(reads) == 4
    CaptureWriter.resume(w.path, known=first.book)
    assert len(reads) == 4


def test_a_chunk_moved_out_is_owed_and_one_moved_back_is_read(tmp_path, reads):
    w = capture(tmp_path, poses=5)
    shutil.move(w.path / "chunk-000002", tmp_path / "aside")
    out = CaptureWriter.resume(w.path, known=w.book)
    assert reads == [] and out.retakes == [Retake(2, (0, 1), (2,))] and out.n_published == 8
    shutil.move(tmp_path / "aside", w.path / "chunk-000002")
    back = CaptureWriter.resume(w.path, known=out.book)
    assert reads == ["chunk-000002"] and back.retakes == [] and back.n_published == 10


def test_a_chunk_altered_since_is_read_again_and_refused_when_damaged(tmp_path, reads):
    w = capture(tmp_path, poses=4)
    hists = w.path / "chunk-000001" / "hists.npy"
    before = os.stat(hists)
    with open(hists, "r+b") as f:  # zeroed in place (a power cut): as long as before, its mtime set back
        f.write(b"\0" * 16)
    os.utime(hists, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert os.stat(hists).st_size == before.st_size and os.stat(hists).st_mtime_ns == before.st_mtime_ns
    with pytest.raises(CaptureError, match=r"chunk-000001/hists\.npy: not a \.npy file"):
        CaptureWriter.resume(w.path, known=w.book)
    assert reads == ["chunk-000001"]


def test_a_chunk_replaced_under_its_name_is_read_again(tmp_path, reads):
    w = capture(tmp_path, poses=3)
    other = capture(tmp_path, poses=3, frames=1, name="other")
    shutil.rmtree(w.path / "chunk-000002")
    shutil.copytree(other.path / "chunk-000002", w.path / "chunk-000002")  # pose 2's frame 0 only
    again = CaptureWriter.resume(w.path, known=w.book)
    assert reads == ["chunk-000002"] and again.retakes == [Retake(2, (1,), None)] and again.n_published == 5


def test_a_book_of_another_capture_is_not_used(tmp_path, reads):
    w = capture(tmp_path, poses=3)
    other = capture(tmp_path, poses=3, name="other")
    CaptureWriter.resume(w.path, known=other.book)
    assert reads == ["chunk-000000", "chunk-000001", "chunk-000002"]
