"""The next_views.json format: sorted best first, written atomically, read back exactly, and every malformed file
refused in one line that names it."""

from __future__ import annotations

import datetime as dt
import json

import numpy as np
import pytest

from spadscan.protocol.errors import CaptureError
from spadscan.protocol.next_views import (FILE, candidate_poses, ranked, read_next_views, too_close,
                                          view_angles_deg, write_next_views)

SCHEDULE = {"radius_m": 0.5, "target": [0.0, 0.0, 0.1], "min_elevation_deg": 10.0, "max_elevation_deg": 80.0}


def test_round_trip_best_first(tmp_path):
    cand = candidate_poses(SCHEDULE, 64)
    scores = np.random.default_rng(0).random(64)
    write_next_views(tmp_path, ranked(cand, scores, 17, "coverage"))
    nv = read_next_views(tmp_path)
    assert nv.pose_count == 17 and nv.measure == "coverage" and abs(nv.age_s()) < 60
    order = np.argsort(-scores, kind="stable")
    np.testing.assert_array_equal(nv.scores, scores[order])
    np.testing.assert_array_equal(nv.poses, cand[order])
    assert [p.name for p in tmp_path.iterdir()] == [FILE]  # no temporary file left


def test_candidates_cover_the_band_and_look_at_the_target():
    cand = candidate_poses(SCHEDULE)
    assert cand.shape == (512, 4, 4)
    d = cand[:, :3, 3] - SCHEDULE["target"]
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 0.5)
    elev = np.degrees(np.arcsin(d[:, 2] / 0.5))
    assert 10 <= elev.min() < 11 and 79 < elev.max() <= 80
    np.testing.assert_allclose(np.einsum("ni,ni->n", cand[:, :3, 2], -d / 0.5), 1.0)
    # Dense: every candidate has a neighbour within ~6 degrees.
    a = view_angles_deg(cand, cand, SCHEDULE["target"]) + 180 * np.eye(512)
    assert a.min(axis=1).max() < 7.0
    with pytest.raises(CaptureError, match="lacks 'radius_m'"):
        candidate_poses({"target": [0, 0, 0]})


def test_too_close_by_angle_from_the_target():
    cand = candidate_poses(SCHEDULE, 100)
    assert not too_close(cand, np.zeros((0, 4, 4)), SCHEDULE["target"], 5.0).any()
    close = too_close(cand, cand[:1], SCHEDULE["target"], 5.0)
    assert close[0] and close.sum() < 5


def _file(tmp_path, **change):
    write_next_views(tmp_path, ranked(candidate_poses(SCHEDULE, 8), np.arange(8.0), 3, "x"))
    data = json.loads((tmp_path / FILE).read_text())
    for key, value in change.items():
        if value is None:
            del data[key]
        else:
            data[key] = value
    (tmp_path / FILE).write_text(json.dumps(data))


@pytest.mark.parametrize("change, message", [
    ({"format": "other"}, "not a next-views file"),
    ({"version": 2}, "version 2 is not one this reader knows"),
    ({"pose_count": -1}, "pose_count -1 must be an integer >= 0"),
    ({"pose_count": True}, "pose_count True must be an integer"),
    ({"created_utc": "yesterday"}, "created_utc 'yesterday' must be an ISO 8601 time"),
    ({"created_utc": "2026-01-01T00:00:00"}, "lacks its UTC offset"),
    ({"candidates": []}, "candidates must be a list of 1..100000"),
    ({"candidates": [{"pose": [[1, 0, 0, 0]] * 4, "score": 1}]}, "candidate 0: pose is not a rigid transform"),
    # a mirror: orthonormal, but a left-handed frame no arm can take
    ({"candidates": [{"pose": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]], "score": 1}]},
     "candidate 0: pose is not a rigid transform"),
    ({"candidates": [{"pose": "up", "score": 1}]}, "candidate 0: pose must be a 4x4 array"),
    ({"candidates": [{"pose": np.eye(4).tolist(), "score": float("nan")}]}, "score nan must be a finite number"),
    ({"candidates": [{"pose": np.eye(4).tolist()}]}, "candidate 0 must be an object with 'pose' and 'score'"),
    ({"candidates": [{"pose": [[1e400, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "score": 1}]},
     "candidate 0: pose holds non-finite values"),
], ids=lambda v: str(v)[:30])
def test_a_malformed_file_is_one_line_naming_it(tmp_path, change, message):
    _file(tmp_path, **change)
    with pytest.raises(CaptureError) as err:
        read_next_views(tmp_path)
    text = str(err.value)
    assert message in text and str(tmp_path / FILE) in text and "\n" not in text


def test_missing_and_truncated(tmp_path):
    with pytest.raises(CaptureError, match="next_views.json: missing"):
        read_next_views(tmp_path)
    _file(tmp_path)
    text = (tmp_path / FILE).read_text()
    (tmp_path / FILE).write_text(text[:100])
    with pytest.raises(CaptureError, match="unreadable JSON"):
        read_next_views(tmp_path)


def test_a_ranking_with_non_finite_scores_is_never_written(tmp_path):
    with pytest.raises(CaptureError, match="finite score"):
        ranked(candidate_poses(SCHEDULE, 4), [1.0, np.inf, 0.0, 2.0], 0)
    assert not (tmp_path / FILE).exists()


def test_age_against_its_clock():
    old = (dt.datetime.now(dt.timezone.utc) - dt.timedelta(seconds=90)).isoformat()
    nv = ranked(candidate_poses(SCHEDULE, 2), [0.0, 1.0], 0, created_utc=old)
    assert 89 < nv.age_s() < 120


def test_a_daemon_resuming_the_scan_meanwhile_does_not_break_the_write(tmp_path, monkeypatch):
    """The daemon drops its own half-written files (`.tmp-` names) whenever it reopens a scan (a resume, a restart);
    a ranking the worker is writing at that moment must still land."""
    import os

    from spadscan.protocol.capture_format import Measurement
    from spadscan.protocol.capture_writer import CaptureWriter
    from spadscan.protocol.sensor_presets import sensor_preset

    sensor = sensor_preset("lcspc-sim")
    writer = CaptureWriter.create(tmp_path / "scan", sensor, chunk_size=1)
    writer.append(Measurement(np.zeros((1, sensor.n_bins), np.uint32), np.eye(4), 0))
    writer.flush()
    replace, resumed = os.replace, []

    def the_daemon_resumes_first(src, dst):  # between the temporary file's write and its rename
        if not resumed:
            resumed.append(str(src))
            CaptureWriter.resume(tmp_path / "scan")
        return replace(src, dst)

    monkeypatch.setattr(os, "replace", the_daemon_resumes_first)
    write_next_views(tmp_path / "scan", ranked(candidate_poses(SCHEDULE, 8), np.arange(8.0), 1))
    assert resumed and read_next_views(tmp_path / "scan").pose_count == 1
