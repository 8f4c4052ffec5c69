"""The reply to an abort gives the pose the scan stopped at, under the keys `ctl status` and the pause reply give a
scan's pose (`pose` of `poses`, `progress` i/n): the poses its capture holds; `ctl abort` says it in its line."""

from __future__ import annotations

import shutil

from spadscan.cli import main
from spadscan.protocol.capture_reader import CaptureReader

from test_runner import daemon_runner, make_cfg, paused_after, sphere, until  # noqa: F401  (sphere: a fixture)

VIEWS = 40


def poses_held(folder) -> int:
    """The poses the capture at `folder` holds (published in order, 2 frames a pose: make_cfg's)."""
    return len(CaptureReader(folder).load().meta) // 2


def test_the_abort_reply_of_a_paused_scan_gives_the_pose_it_stopped_at(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=VIEWS)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "mug", runner.pause, poses=3)
            return await runner.status_now(), await runner.abort("wrong object")

    paused, aborted = arun(scenario())
    assert aborted["aborted"] == "mug" and aborted["scan"] is None and aborted["state"] == "idle", aborted
    at = paused["pose"]
    assert (aborted["pose"], aborted["poses"], aborted["progress"]) == (at, VIEWS, f"{at}/{VIEWS}"), aborted
    assert paused["progress"] == aborted["progress"], (paused, aborted)  # the same key and meaning as status
    assert poses_held(tmp_path / "caps" / "mug") == at


def test_the_abort_reply_of_a_running_scan_gives_the_poses_its_capture_holds(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=VIEWS)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("mug")
            await until(lambda: runner.job.next_pose >= 3, "three poses")
            return await runner.abort()

    aborted = arun(scenario())
    held = poses_held(tmp_path / "caps" / "mug")
    assert held >= 3 and (aborted["pose"], aborted["progress"]) == (held, f"{held}/{VIEWS}"), (held, aborted)


def test_a_chunk_moved_out_during_the_pause_lowers_the_pose_the_abort_reply_gives(arun, tmp_path,
                                                                                  sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = tmp_path / "caps" / "mug"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "mug", runner.pause, poses=3)
            before = runner.status()
            newest = sorted(folder.glob("chunk-*"))[-1]
            shutil.move(newest, tmp_path / newest.name)  # (one pose a chunk)
            return before, await runner.abort()

    before, aborted = arun(scenario())
    assert aborted["pose"] == before["pose"] - 1 == poses_held(folder), (before, aborted)


def test_ctl_abort_says_the_pose_the_scan_stopped_at(tmp_path, monkeypatch, capsys):
    import spadscan.daemon.client as client

    reply = {"ok": True, "state": "idle", "scan": None, "last_error": None, "aborted": "mug", "abort_recorded": True,
             "pose": 38, "poses": 128, "progress": "38/128"}
    monkeypatch.setattr(client, "call", lambda path, op, timeout, **request: dict(reply))
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), "abort"]) == 0
    assert capsys.readouterr().out == "scan 'mug' aborted at pose 38/128\n"
