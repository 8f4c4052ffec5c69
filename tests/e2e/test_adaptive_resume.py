"""kill -9 of the daemon in the middle of an adaptive scan that a stand-in live reconstruction steers, a restarted
daemon, `ctl resume`: every pose once, each at the row schedule.npy names, each with why it was taken, and the views
ranked before and after the crash both followed."""

from __future__ import annotations

import collections
import threading

import numpy as np
import pytest

from e2e_helpers import assert_every_pose_once, published_prefix, wait_for
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.next_views import candidate_poses, ranked, view_angles_deg, write_next_views

VIEWS, K, INITIAL = 24, 2, 4
SCAN = {"schedule": "adaptive", "views": VIEWS, "initial_views": INITIAL, "frames_per_pose": K, "chunk_size": K,
        "min_view_spacing_deg": 8.0}
ARM = {"motion_time_s": 0.05}  # slow enough that a kill lands mid-scan


class StandInRanking(threading.Thread):
    """Keeps `<folder>/next_views.json` fresh while the test runs, as a live reconstruction would: the same ranking
    (a fixed random score per candidate) rewritten with the capture's published pose count."""

    def __init__(self, folder):
        super().__init__(daemon=True)
        self.folder, self.stop = folder, threading.Event()

    def run(self) -> None:
        while not self.stop.wait(0.02):
            try:
                reader = CaptureReader(self.folder)
                published = len({int(i) for name in reader.chunk_names()
                                 for i in reader.read_chunk(name).pose_indices})
                cand = candidate_poses(reader.manifest["schedule"])
                score = np.random.default_rng(7).random(len(cand))
                write_next_views(self.folder, ranked(cand, score, published, "stand-in"))
            except (CaptureError, OSError):  # the folder not made yet, or a chunk being published: next time
                continue


@pytest.mark.slow
def test_an_adaptive_scan_resumes_after_kill_9_with_every_pose_once(make_daemon, tmp_path):
    folder = tmp_path / "caps" / "nbv"
    ranking = StandInRanking(folder)
    ranking.start()
    try:
        first = make_daemon(arm=ARM, scan=SCAN).start()
        r = first.ctl("scan", "--name", "nbv")
        assert r.returncode == 0, r.stderr
        # Killed once a ranked pose has been taken (the stand-in may be slow to write its first file on a busy
        # machine, and the daemon never waits for it): the crash then lands between ranked poses.
        wait_for(lambda: ((s := first.status())["scan"] == "nbv" and (s.get("pose") or 0) >= INITIAL + 4
                          and s.get("views_chosen", {}).get("adaptive", 0) >= 1),
                 "a pose taken from the ranking", 60.0)
        first.kill9()
        before, digests = published_prefix(folder)
        assert CaptureReader(folder).state == "running"

        second = make_daemon(arm=ARM, scan=SCAN).start()
        status = second.status()
        assert (status["state"], status["pose"], status["schedule"]) == ("paused", len(before), "adaptive"), status
        assert sum(status["views_chosen"].values()) == len(before)
        assert second.ctl("resume").returncode == 0
        r = second.ctl("wait", "nbv")
        assert r.returncode == 0, r.stderr + second.log()
    finally:
        ranking.stop.set()
        ranking.join()
    data = assert_every_pose_once(folder, VIEWS, K)  # and each measurement at the row schedule.npy names
    _, after = published_prefix(folder)
    assert all(after[name] == digest for name, digest in digests.items()), "a chunk published before the crash changed"
    why = {m["pose_index"]: m["view_choice"]["why"] for m in data.meta}
    assert [why[i] for i in range(INITIAL)] == ["initial"] * INITIAL
    assert any(why[i] == "adaptive" for i in range(INITIAL, len(before)))
    assert any(why[i] == "adaptive" for i in range(len(before), VIEWS)), "the ranking is followed after the resume"
    counts = collections.Counter(why.values())
    assert CaptureReader(folder).manifest["view_choices"] == dict(sorted(counts.items()))
    poses = data.poses[::K]
    angles = view_angles_deg(poses, poses, [0.0, 0.0, 0.1]) + np.eye(len(poses)) * 180
    assert angles.min() > 1.0, "a pose was taken twice"
    assert second.stop() == 0, second.log()
