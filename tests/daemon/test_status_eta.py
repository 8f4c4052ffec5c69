"""`ctl status` `eta_s`: the seconds a scan has left at its measured pace (the poses still to take at the pose rate
of the last 10 s), null before a rate is measured and while the scan is paused; `rate_unit` says what `rate_hz`
counts (frames, not poses)."""

from __future__ import annotations

import numpy as np
import pytest

from spadscan.daemon.config import ScanConfig
from spadscan.daemon.runner import scan_eta_s
from spadscan.daemon.scan_job import ScanJob

from test_runner import daemon_runner, make_cfg, until, sphere  # noqa: F401  (sphere: the fixture)
from test_status_rate import clock, job_at  # noqa: F401  (clock: the fixture)


def test_the_time_left_is_the_poses_left_at_the_pose_rate_of_the_last_seconds(clock):  # noqa: F811
    job = job_at(100.0, 4.0, 20)  # 100 poses of 2 frames, 4 frames/s from t=100 to t=120: 2 poses a second
    job.scan = ScanConfig(frames_per_pose=2)
    job.next_pose = 40
    clock.t = 120.0
    assert scan_eta_s(job) == pytest.approx(30.0)  # 60 poses at 2 a second
    job.owed = [3, 7]  # two poses to take again before it goes on
    assert scan_eta_s(job) == pytest.approx(31.0)
    clock.t = 125.0  # no frame for 5 s (a silent sensor): half the rate, twice the time
    assert scan_eta_s(job) == pytest.approx(62.0)
    clock.t = 131.0  # nothing for more than the window: the pace is not known
    assert scan_eta_s(job) is None


def test_the_time_left_is_unknown_before_the_scan_has_taken_frames(clock):  # noqa: F811
    job = ScanJob(name="j", path=None, scan=ScanConfig(), sensor_poses=np.zeros((4, 4, 4)),
                  tcp_poses=np.zeros((4, 4, 4)), hand_eye=np.eye(4))
    clock.t = 5.0
    assert scan_eta_s(job) is None


def test_status_says_the_time_left_while_scanning_and_none_while_paused(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=40)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("timed")
            await until(lambda: runner.job.next_pose >= 3 and runner.status()["eta_s"] is not None,
                        "a pace measured after three poses")
            scanning = runner.status()
            await runner.pause()
            await until(lambda: runner.state == "paused", "the operator's pause")
            paused = runner.status()
            await runner.abort()
            return scanning, paused

    scanning, paused = arun(scenario())
    assert scanning["state"] == "scanning" and scanning["rate_unit"] == "frames/s", scanning
    left = (scanning["poses"] - scanning["pose"]) * scanning["frames_per_pose"] / scanning["rate_hz"]
    assert scanning["eta_s"] == pytest.approx(left, rel=0.05, abs=0.2), scanning
    assert paused["state"] == "paused" and "eta_s" in paused and paused["eta_s"] is None, paused
    assert paused["progress"] == f"{paused['pose']}/40" and "rate_hz" in paused and "elapsed_s" in paused
