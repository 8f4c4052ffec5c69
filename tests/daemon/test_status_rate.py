"""`ctl status` `rate_hz`: frames published per second over the last 10 s, counted back from now, and null while the
scan takes no frames (paused by the operator or by a fault), as the dashboard shows no rate for a scan that is not
running. A scan whose frames stop coming shows its rate falling, not the rate it had; after a resume the pause is not
counted in."""

from __future__ import annotations

import types

import numpy as np
import pytest

from spadscan.daemon import scan_job
from spadscan.daemon.arm.sim import SimArmFaults
from spadscan.daemon.config import ScanConfig
from spadscan.daemon.scan_job import ScanJob

from test_runner import daemon_runner, make_cfg, until, sphere  # noqa: F401  (sphere: the fixture)


@pytest.fixture
def clock(monkeypatch):
    """The monotonic clock scan_job reads, set by the test (`clock.t`)."""
    fake = types.SimpleNamespace(t=0.0)
    monkeypatch.setattr(scan_job, "time", types.SimpleNamespace(monotonic=lambda: fake.t))
    return fake


def job_at(t0: float, frames_per_s: float, seconds: int) -> ScanJob:
    """A job that began scanning at t0 (monotonic s) and published a pose of 2 frames every 2 / frames_per_s s for
    `seconds`."""
    job = ScanJob(name="j", path=None, scan=ScanConfig(), sensor_poses=np.zeros((100, 4, 4)),
                  tcp_poses=np.zeros((100, 4, 4)), hand_eye=np.eye(4))
    job.scanning_since = t0
    job.history.append((t0, 0))
    step = 2.0 / frames_per_s
    for k in range(1, int(seconds / step) + 1):
        publish(job, t0 + k * step, 2)
    return job


def publish(job: ScanJob, t: float, frames: int) -> None:
    job.frames += frames
    job.history.append((t, job.frames))


def rate_at(job: ScanJob, clock, t: float) -> float:
    clock.t = t
    return job.rate_hz()


def test_the_rate_is_counted_back_from_now_and_falls_when_frames_stop(clock):
    job = job_at(100.0, 2.0, 20)  # 2 frames/s from t=100 to t=120, then nothing (a silent sensor)
    assert rate_at(job, clock, 120.0) == pytest.approx(2.0)
    assert rate_at(job, clock, 125.0) == pytest.approx(1.0)  # the last 10 s held 5 s of frames
    assert rate_at(job, clock, 131.0) == 0.0  # nothing for more than the window


def test_the_rate_after_a_resume_leaves_the_pause_out(clock):
    job = job_at(100.0, 2.0, 20)
    clock.t = 125.0  # paused from t=120 until the resume at t=125: a pause shorter than the window
    job.mark_scanning()
    publish(job, 126.0, 2)
    publish(job, 127.0, 2)
    assert rate_at(job, clock, 127.0) == pytest.approx(2.0)  # 4 frames in the 2 s since the resume, none paused


def test_the_rate_is_zero_before_the_scan_has_begun_taking_frames(clock):
    job = ScanJob(name="j", path=None, scan=ScanConfig(), sensor_poses=np.zeros((4, 4, 4)),
                  tcp_poses=np.zeros((4, 4, 4)), hand_eye=np.eye(4))
    assert rate_at(job, clock, 5.0) == 0.0


def test_status_has_a_rate_only_while_the_scan_takes_frames(arun, tmp_path, sphere):  # noqa: F811
    """Paused by a fault (a protective stop at the 4th move) and by the operator: rate_hz is null (the key stays);
    scanning, it is a rate counted since the resume."""
    cfg = make_cfg(tmp_path, views=30)

    async def scenario():
        async with daemon_runner(cfg, sphere, faults=SimArmFaults(protective_stop_on_moves=(4,)),
                                 motion_time_s=0.01) as runner:
            await runner.start("rated")
            await until(lambda: runner.state == "paused", "the protective stop's pause")
            faulted = runner.status()
            await runner.resume()
            await until(lambda: runner.job.next_pose >= faulted["pose"] + 2, "two poses after the resume")
            scanning = runner.status()
            await runner.pause()
            await until(lambda: runner.state == "paused", "the operator's pause")
            paused = runner.status()
            await runner.abort()
            return faulted, scanning, paused

    faulted, scanning, paused = arun(scenario())
    assert faulted["state"] == "paused" and "protective stop" in faulted["reason"], faulted
    assert "rate_hz" in faulted and faulted["rate_hz"] is None, faulted
    assert scanning["state"] == "scanning" and scanning["rate_hz"] > 0, scanning
    assert paused["state"] == "paused" and paused["reason"] == "paused by user", paused
    assert "rate_hz" in paused and paused["rate_hz"] is None, paused
