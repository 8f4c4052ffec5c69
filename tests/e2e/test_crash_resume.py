"""kill -9 of the daemon mid-scan, a restarted daemon, and the scan resumed (by `ctl resume`, or by itself with
`auto_resume`): every pose exactly once in the capture, each with its K frames, at its planned pose."""

from __future__ import annotations

import collections
import json

import pytest

from e2e_helpers import assert_every_pose_once, published_prefix
from spadscan.protocol.capture_reader import CaptureReader

VIEWS, K = 30, 3
SCAN = {"views": VIEWS, "frames_per_pose": K, "chunk_size": K}
ARM = {"motion_time_s": 0.05}  # slow enough that a kill lands mid-scan


def start_and_kill(daemon, folder, at_pose: int) -> tuple[list[int], dict]:
    """Kill -9 the daemon once the scan in `folder` has published `at_pose` poses. Checks that no published pose
    was lost and no half pose was published; returns (published poses, chunk digests)."""
    seen = daemon.wait_pose(folder.name, at_pose)["pose"]
    daemon.kill9()
    poses, digests = published_prefix(folder)
    assert poses == list(range(len(poses))), "published poses are a prefix of the plan"
    assert len(poses) >= seen, "a pose the daemon reported published is gone"
    per_pose = collections.Counter(CaptureReader(folder).load().pose_indices.tolist())
    assert set(per_pose.values()) == {K}, f"a pose was published without all its {K} frames: {per_pose}"
    assert CaptureReader(folder).state == "running"
    return poses, digests


@pytest.fixture
def captures(tmp_path):
    return tmp_path / "caps"


@pytest.mark.slow
def test_kill_9_restart_ctl_resume_every_pose_once(make_daemon, captures):
    first = make_daemon(arm=ARM, scan=SCAN).start()
    r = first.ctl("scan", "--name", "crash")
    assert r.returncode == 0, r.stderr
    poses, digests = start_and_kill(first, captures / "crash", 5)

    second = make_daemon(arm=ARM, scan=SCAN).start()  # auto_resume = false: it takes the scan over paused
    status = second.status()
    assert (status["state"], status["scan"], status["pose"]) == ("paused", "crash", len(poses)), status
    assert "interrupted" in status["reason"]
    r = second.ctl("resume")
    assert r.returncode == 0, r.stderr
    r = second.ctl("wait", "crash")
    assert r.returncode == 0 and json.loads(r.stdout)["state"] == "complete", r.stderr + second.log()
    data = assert_every_pose_once(captures / "crash", VIEWS, K)
    assert len(data.hists) == VIEWS * K
    _, after = published_prefix(captures / "crash")
    assert all(after[name] == digest for name, digest in digests.items()), "a chunk published before the crash changed"
    assert second.stop() == 0, second.log()


@pytest.mark.slow
def test_kill_9_twice_auto_resume_every_pose_once(make_daemon, captures):
    auto = {"auto_resume": True}
    first = make_daemon(arm=ARM, scan=SCAN, top=auto).start()
    first.call("scan", name="auto")
    poses1, _ = start_and_kill(first, captures / "auto", 4)

    second = make_daemon(arm=ARM, scan=SCAN, top=auto).start()  # resumes by itself
    poses2, digests = start_and_kill(second, captures / "auto", len(poses1) + 4)
    assert poses2[: len(poses1)] == poses1

    third = make_daemon(arm=ARM, scan=SCAN, top=auto).start()
    r = third.ctl("wait", "auto")
    assert r.returncode == 0 and json.loads(r.stdout)["state"] == "complete", r.stderr + third.log()
    assert_every_pose_once(captures / "auto", VIEWS, K)
    _, after = published_prefix(captures / "auto")
    assert all(after[name] == digest for name, digest in digests.items())
    assert third.status()["state"] == "idle"
    assert third.stop() == 0, third.log()
