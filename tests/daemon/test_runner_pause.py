"""What `ctl pause` tells the operator matches what the scan does: the pose in flight is finished and published
first, and the reply and the log say at which pose the scan will stop."""

from __future__ import annotations

import asyncio
import logging
import re

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.runner import ScanRunner

from test_runner import make_cfg, make_rig, sphere, until  # noqa: F401  (sphere: a fixture)


def test_pause_says_where_it_stops(arun, tmp_path, sphere, caplog):  # noqa: F811
    caplog.set_level(logging.INFO, logger="spadscan.daemon")
    cfg = make_cfg(tmp_path, views=60, frames_per_pose=1, settle_s=0.08)

    async def scenario():
        arm, sensor = make_rig(cfg, sphere, motion_time_s=0.02, frame_time_s=0.02)
        seen = []
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                await runner.start("pz")
                for offset in (0.0, 0.03, 0.06, 0.09, 0.12):  # at every stage of a pose: move, settle, frames
                    published = runner.job.next_pose
                    await until(lambda: runner.job.next_pose > published, "a pose published")
                    await asyncio.sleep(offset)
                    reply = await runner.pause()
                    await until(lambda: runner.state == "paused", "paused")
                    seen.append((reply["progress"], reply.get("pausing_at"), runner.status()["progress"]))
                    await runner.resume()
                await runner.abort()
            finally:
                await runner.shutdown()
        return seen

    seen = arun(scenario())
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    requested = [m for m in said if "pause requested" in m]
    paused = [m for m in said if m.startswith("scan pz paused by user")]
    assert len(requested) == len(paused) == len(seen) == 5, said
    for (at_request, pausing_at, stopped), req, stop in zip(seen, requested, paused):
        assert pausing_at == stopped, seen  # the reply said where the scan would stop
        assert req == f"scan pz: pause requested at pose {at_request}; pausing at pose {stopped}, once the pose in " \
                      f"flight is published", said
        assert stop == f"scan pz paused by user at pose {stopped}"
        gap = int(stopped.split("/")[0]) - int(at_request.split("/")[0])
        assert 0 <= gap <= 2, seen  # at most one pose waiting to be written and one being captured
    assert any(re.search(r"pose (\d+)/60; pausing at pose (?!\1/)", m) for m in requested), requested
