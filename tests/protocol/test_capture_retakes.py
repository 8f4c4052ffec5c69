"""A resumed capture that lacks measurements before its first unpublished pose (a damaged chunk the operator moved
out) lists them in `CaptureWriter.retakes`, each with free chunk numbers that keep the chunks' name order in pose
order; publishing them makes it whole again, and it cannot be marked complete before."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from spadscan.protocol.capture_format import Measurement
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter, Retake, count_stock, plan_retakes
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.sensor_presets import sensor_preset

SENSOR = sensor_preset("tmf8820")


def frame(pose: int, k: int, tag: str = "first") -> Measurement:
    hist = np.full((SENSOR.n_zones, SENSOR.n_bins), 10 * pose + k + 1)
    return Measurement(hist, np.eye(4), pose, k, np.ones(SENSOR.n_bins), {"tag": tag})


def capture(tmp_path, poses: int, frames: int, chunk_size: int, planned: int = 8):
    """A capture of `poses` of `planned` poses x `frames` frames, each pose flushed as the daemon does."""
    path = tmp_path / "scan"
    w = CaptureWriter.create(path, SENSOR, planned_poses=np.stack([np.eye(4)] * planned), chunk_size=chunk_size,
                             frames_per_pose=frames)
    for i in range(poses):
        for k in range(frames):
            w.append(frame(i, k))
        w.flush()
    return path


def move_out(path, *numbers) -> None:
    for n in numbers:
        shutil.move(path / f"chunk-{n:06d}", path.parent / f"moved-{n}")


def pairs_in_name_order(path) -> list[tuple[int, int]]:
    data = CaptureReader(path).load()
    return [(m["pose_index"], m["frame"]) for m in data.meta]


def test_a_pose_moved_out_is_taken_again_under_its_number_and_the_capture_stays_in_pose_order(tmp_path):
    path = capture(tmp_path, poses=5, frames=2, chunk_size=2, planned=6)
    move_out(path, 1, 3)
    w = CaptureWriter.resume(path)
    assert w.retakes == [Retake(1, (0, 1), (1,)), Retake(3, (0, 1), (3,))]
    with pytest.raises(CaptureError, match=r"not complete: pose\(s\) 1, 3 lack frames"):
        w.finish("complete")
    for r in list(w.retakes):
        w.publish_retake(r, [frame(r.pose, k, "again") for k in r.frames])
    for k in range(2):
        w.append(frame(5, k))
    w.finish("complete")
    assert pairs_in_name_order(path) == [(i, k) for i in range(6) for k in range(2)]
    assert [m["tag"] for m in CaptureReader(path).read_chunk("chunk-000003").meta] == ["again", "again"]
    assert CaptureWriter.resume(path).retakes == []


def test_a_pose_split_over_chunks_takes_only_its_missing_frames_again(tmp_path):
    # chunk 2k: pose k frame 0; chunk 2k+1: frame 1
    path = capture(tmp_path, poses=3, frames=2, chunk_size=1, planned=3)
    move_out(path, 3, 5)  # pose 1 frame 1 (between chunks), pose 2 frame 1 (the last chunk)
    w = CaptureWriter.resume(path)
    assert w.retakes == [Retake(1, (1,), (3,)), Retake(2, (1,), None)]
    assert w.next_pose_index == 3
    for r in list(w.retakes):
        w.publish_retake(r, [frame(r.pose, k, "again") for k in r.frames])
    w.finish("complete")
    assert sorted(pairs_in_name_order(path)) == [(i, k) for i in range(3) for k in range(2)]
    assert [p for p, _ in pairs_in_name_order(path)] == [0, 0, 1, 1, 2, 2]  # poses in name order


def test_measurements_that_do_not_match_the_retake_are_refused(tmp_path):
    path = capture(tmp_path, poses=3, frames=2, chunk_size=2)
    move_out(path, 1)
    w = CaptureWriter.resume(path)
    (r,) = w.retakes
    with pytest.raises(CaptureError, match="do not retake pose 1"):
        w.publish_retake(r, [frame(1, 0)])
    assert not (path / "chunk-000001").exists()


def test_poses_that_cannot_be_put_back_in_order_are_refused_in_one_line():
    chunks = [(0, [(0, 0)]), (1, [(2, 0)])]  # pose 1 missing, and no number free between chunks 0 and 1
    with pytest.raises(CaptureError) as refused:
        plan_retakes(chunks, 1, 4, "caps/s")
    assert str(refused.value) == ("caps/s: pose 1 lacks frame(s) 0 and cannot take them again in order: no chunk "
                                  "number is free between chunk-000000 and chunk-000001 (a capture lists its poses "
                                  "in chunk order; were its chunks renamed?)")


def test_a_whole_capture_owes_nothing():
    assert plan_retakes([(0, [(0, 0), (0, 1)]), (1, [(1, 0), (1, 1)])], 2, 2, "x") == []
    assert plan_retakes([(0, [(0, None)]), (1, [(1, None)])], 3, 2, "x") == []  # no frame numbers: taken as whole


def test_a_pose_that_needs_more_frames_than_a_chunk_holds_gets_as_many_chunk_numbers():
    # 3 frames a pose, 2 measurements a chunk: pose 1 (chunks 2 and 3) moved out needs both numbers back
    chunks = [(0, [(0, 0), (0, 1)]), (1, [(0, 2)]), (4, [(2, 0), (2, 1)]), (5, [(2, 2)])]
    assert plan_retakes(chunks, 3, 2, "x") == [Retake(1, (0, 1, 2), (2, 3))]


def test_a_pose_whose_first_frame_is_moved_out_takes_it_again_before_its_later_frames(tmp_path):
    path = capture(tmp_path, poses=3, frames=2, chunk_size=1, planned=3)  # chunk 2: pose 1 frame 0
    move_out(path, 2)
    w = CaptureWriter.resume(path)
    assert w.retakes == [Retake(1, (0,), (2,))]
    (r,) = w.retakes
    w.publish_retake(r, [frame(1, 0, "again")])
    w.finish("complete")
    assert pairs_in_name_order(path) == [(i, k) for i in range(3) for k in range(2)]


def test_the_next_pose_follows_the_highest_published_one_when_a_middle_chunk_is_gone():
    stock = count_stock([(0, [(0, 0)]), (1, [(1, 0)]), (3, [(3, 0)]), (4, [(4, 0)])], {"chunk_size": 1}, "x")
    assert stock.next_pose == 5 and stock.poses == frozenset({0, 1, 3, 4}) and stock.published == 4
    assert stock.retakes == (Retake(2, (0,), (2,)),)


def test_a_chunk_put_back_under_a_retake_s_number_is_not_replaced(tmp_path):
    """The operator moves a chunk out, the daemon resumes, then the chunk is put back: the retake is refused, and
    the chunk put back stays as it is."""
    path = capture(tmp_path, poses=3, frames=2, chunk_size=2, planned=3)
    move_out(path, 1)
    w = CaptureWriter.resume(path)
    (r,) = w.retakes
    shutil.move(path.parent / "moved-1", path / "chunk-000001")
    with pytest.raises(CaptureError, match="chunk-000001: already published; a chunk is never replaced"):
        w.publish_retake(r, [frame(1, k, "again") for k in range(2)])
    assert [m["tag"] for m in CaptureReader(path).read_chunk("chunk-000001").meta] == ["first", "first"]
