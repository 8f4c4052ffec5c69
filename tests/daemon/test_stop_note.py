"""The last line a daemon stopped mid-scan logs (`scan NAME left at pose i/n`) says what the capture holds on disk:
a pose whose publish was still landing when the scan was stopped is counted once it has landed, as the restarted
daemon counts it. The interleaving is forced with hooks, not timing."""

from __future__ import annotations

import asyncio
import logging
import threading

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.runner import ScanRunner
from spadscan.protocol.capture_writer import CaptureWriter

from test_runner import make_cfg, make_rig, sphere, until  # noqa: F401  (sphere: a fixture)

VIEWS = 40
HELD = 3  # the pose whose publish the writer thread holds until the stop has begun


def test_the_stop_note_counts_a_publish_that_landed_as_the_scan_was_stopped(arun, tmp_path, sphere, caplog,
                                                                            monkeypatch):  # noqa: F811
    """Pose HELD's publish is held on the writer thread until the scan task waits for it and the shutdown has
    cancelled that wait; then it lands. The note must count it (the capture holds poses 0..HELD), as the next
    daemon's takeover does."""
    caplog.set_level(logging.INFO, logger="spadscan.daemon")
    cfg = make_cfg(tmp_path, views=VIEWS)
    entered, release = threading.Event(), threading.Event()
    waiting: list[int] = []  # the poses whose publish the scan task has begun to wait for
    real_publish, real_landed = ScanRunner._publish, ScanRunner._landed

    def held_publish(writer, measurements):
        if measurements[0].pose_index == HELD:
            entered.set()
            release.wait(timeout=30.0)  # (a bound: the test releases it)
        real_publish(writer, measurements)

    async def noted_landed(publish, i):
        waiting.append(i)
        await real_landed(publish, i)

    monkeypatch.setattr(ScanRunner, "_publish", staticmethod(held_publish))
    monkeypatch.setattr(ScanRunner, "_landed", staticmethod(noted_landed))

    async def scenario():
        arm, sensor = make_rig(cfg, sphere, motion_time_s=0.01)
        async with DeviceSession([arm, sensor]):
            runner = ScanRunner(arm, sensor, cfg)
            try:
                await runner.start("held")
                await until(lambda: entered.is_set() and HELD in waiting, "the scan waiting for the held publish")
                job = runner.job
                stopping = asyncio.ensure_future(runner.shutdown())
                await until(lambda: job.winding_down is not None, "the scan task cancelled")
            finally:
                release.set()
            await stopping
            return job.next_pose

    counted = arun(scenario())
    on_disk = CaptureWriter.resume(tmp_path / "caps" / "held").next_pose_index  # what the next daemon counts
    assert on_disk == HELD + 1, on_disk
    left = [r.getMessage() for r in caplog.records if r.getMessage().startswith("scan held left")]
    assert left == [f"scan held left at pose {on_disk}/{VIEWS}, resumable: start the daemon again, then "
                    f"`spadscan ctl resume`"], left
    assert counted == on_disk
    assert caplog.records[-1].getMessage() == left[0]  # the last word on the scan

