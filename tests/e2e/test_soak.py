"""A soak: 2,000 poses through a daemon process with sim backends at zero motion and frame time. Its memory stays
flat (resident set at 500 poses against the end) and it leaks no file descriptors (counted in /proc before and after).
"""

from __future__ import annotations

import collections
import json

import pytest

from e2e_helpers import assert_every_pose_once, rss_kib, settled_fds, tmpfs, wait_for

POSES = 2000
RSS_MARGIN_KIB = 5 * 1024
"""Allowed growth of the resident set from pose 500 to pose 2,000 (measured: under 0.5 MiB). A leaked histogram per
pose alone would add 4.5 KiB x 1,500 = 6.6 MiB; a leaked measurement with its metadata far more."""


def kinds(fds: dict[int, str]) -> collections.Counter:
    """What the fds point at, socket and pipe numbers left out: {'socket': 2, '/dev/null': 1, ...}."""
    return collections.Counter(t.split(":[")[0] for t in fds.values())


@pytest.fixture
def captures(tmp_path, procs):
    """The captures root on a tmpfs where one can be mounted: fsync is then free and the soak measures the daemon,
    not the disk (2,000 poses fsynced on a busy disk take minutes). Otherwise a folder of tmp_path."""
    with tmpfs(tmp_path / "caps", "256m"):
        try:
            yield tmp_path / "caps"
        finally:
            procs.stop_all()


@pytest.mark.slow
def test_soak_2000_poses_memory_flat_no_fd_leak(make_daemon, tmp_path, captures):
    daemon = make_daemon(captures=captures, sensor={"rays_per_zone": 1, "frame_time_s": 0.0},
                         scan={"views": POSES, "frames_per_pose": 1, "chunk_size": 1, "order": "planned"}).start()
    daemon.status()
    fds_before = settled_fds(daemon.pid)
    daemon.call("scan", name="soak")
    daemon.wait_pose("soak", 500, timeout_s=120)
    rss_500 = rss_kib(daemon.pid)
    samples = [rss_500]

    def finished():
        s = daemon.status()
        samples.append(rss_kib(daemon.pid))
        return s["state"] == "idle" and s.get("last_scan") == {"name": "soak", "state": "complete"}

    wait_for(finished, "2,000 poses", timeout_s=240, poll_s=0.5)
    rss_end = rss_kib(daemon.pid)
    growth = rss_end - rss_500
    assert growth < RSS_MARGIN_KIB, f"resident set grew {growth} KiB from pose 500 to {POSES}: {samples}"
    fds_after = settled_fds(daemon.pid)
    assert kinds(fds_after) == kinds(fds_before), f"file descriptors leaked: {fds_before} -> {fds_after}"
    data = assert_every_pose_once(captures / "soak", POSES, 1)
    assert len(data.hists) == POSES
    (tmp_path / "soak.json").write_text(json.dumps({"rss_kib": samples, "fds": fds_after}))
    assert daemon.stop() == 0, daemon.log()
