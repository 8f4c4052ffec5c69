"""What `ctl pause` tells the operator matches what the scan does: the pose in flight is finished and published
first, and the reply and the log say at which pose the scan will stop."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import threading

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.runner import ScanRunner
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import ConfigError

from test_runner import daemon_runner, make_cfg, make_rig, sphere, until  # noqa: F401  (sphere: a fixture)


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
        assert req == f"scan pz: pause requested at pose {at_request}; pausing at pose {stopped}, once the poses " \
                      f"under way are published", said
        assert stop == f"scan pz paused by user at pose {stopped}"
        gap = int(stopped.split("/")[0]) - int(at_request.split("/")[0])
        assert 0 <= gap <= 2, seen  # at most one pose waiting to be written and one being captured
    assert any(re.search(r"pose (\d+)/60; pausing at pose (?!\1/)", m) for m in requested), requested


@contextlib.asynccontextmanager
async def scanning(cfg, sphere, name: str):  # noqa: F811
    """A runner on a quick simulated rig, scanning `name`; shut down on leaving."""
    async with daemon_runner(cfg, sphere, motion_time_s=0.0, frame_time_s=0.01) as runner:
        await runner.start(name)
        yield runner


def test_a_pause_withdrawn_while_the_last_pose_is_published_takes_every_pose(arun, tmp_path, sphere,  # noqa: F811
                                                                              monkeypatch):
    """`ctl resume` after the runner has left its loop for a pause, while the pose in flight is still being written
    (a slow disk): the pause is withdrawn, and the scan was finished as complete with its other poses never taken."""
    cfg = make_cfg(tmp_path, views=12, frames_per_pose=1, settle_s=0.0)
    first, second = threading.Event(), threading.Event()  # set when the two held writes begin
    release_first, release_second = threading.Event(), threading.Event()
    publish = ScanRunner._publish

    def held_publish(writer, measurements):
        if writer.next_pose_index >= 3 and not first.is_set():
            first.set()
            release_first.wait(10)
        elif first.is_set() and not second.is_set():
            second.set()
            release_second.wait(10)
        publish(writer, measurements)

    monkeypatch.setattr(ScanRunner, "_publish", staticmethod(held_publish))

    async def scenario():
        async with scanning(cfg, sphere, "race") as runner:
            try:
                await until(first.is_set, "pose 3 being written")
                await until(lambda: runner.job.in_flight == 4, "pose 4 under way")
                await runner.pause()  # the loop stops after pose 4, once pose 3 has landed
                release_first.set()
                # Pose 4's write begins as the loop leaves for the pause (no await between): the runner now waits
                # for it in its loop's clean-up.
                await until(second.is_set, "pose 4 being written")
                await runner.resume()
                release_second.set()
                return await asyncio.wait_for(runner.wait("race"), 30)
            finally:  # a held write must not hold the shutdown
                release_first.set()
                release_second.set()

    assert arun(scenario())["state"] == "complete"
    assert len(set(CaptureReader(tmp_path / "caps" / "race").load().pose_indices.tolist())) == 12


def test_a_pose_refused_mid_scan_pauses_with_the_reason_not_an_internal_error(arun, tmp_path, sphere,  # noqa: F811
                                                                               monkeypatch, caplog):
    """An adaptive scan taken over under a tightened box finds no pose it may move to: a ConfigError, which paused
    the scan as "internal error: ConfigError: ..." with a traceback in the log, at every resume."""
    cfg = make_cfg(tmp_path, views=6, frames_per_pose=1, settle_s=0.0)
    move = ScanRunner._move

    async def refusing_move(runner, job, i):
        if i == 2:
            raise ConfigError("no pose left in the plan can be reached by a straight move from pose 1 ([arm] limits)")
        return await move(runner, job, i)

    monkeypatch.setattr(ScanRunner, "_move", refusing_move)

    async def scenario():
        async with scanning(cfg, sphere, "refused") as runner:
            await until(lambda: runner.state == "paused", "paused")
            return runner.job.reason

    reason = arun(scenario())
    assert reason.startswith("no pose left in the plan can be reached") and "internal error" not in reason, reason
    assert not any(r.exc_info for r in caplog.records), "no traceback: the operator's config, not a bug"
