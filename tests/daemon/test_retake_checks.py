"""What the daemon checks and says around the retake's way (back to the poses a damaged chunk held, forward again to
the last published pose): every pose of the way against the current [arm] limits before the arm moves; the poses
owed in status after a takeover on a full disk; no pause announced for a takeover resumed at once; and a stop on the
scan's next move that lies on an earlier move of its path too is not mistaken for a stop on the way. Each stop is
forced at a chosen move with hooks, not timing."""

from __future__ import annotations

import errno

import numpy as np

from spadscan.daemon import runner as runner_module
from spadscan.daemon.scan_path import ON_PATH_M, segment_distance
from spadscan.daemon.scan_plan import ScanPlan, tcp_from_sensor
from spadscan.daemon.workspace import check_workspace
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter

from test_retake_way import (interrupted, owing, restarted_with_the_arm_at, stopped_on_the_next_move, visited,
                             VIEWS)
from test_runner import HAND_EYE, check_capture, daemon_runner, make_cfg, until, sphere  # noqa: F401  (the fixture)


def published(folder) -> list[str]:
    return sorted(p.name for p in folder.glob("chunk-*"))


def plan_of(folder) -> np.ndarray:
    """The TCP poses of the scan in `folder`, as a restarted daemon reads them."""
    return tcp_from_sensor(CaptureReader(folder).planned_poses(), np.array(HAND_EYE))


async def refused_at_resume(cfg, sphere, here):  # noqa: F811
    """A daemon on cfg takes the scan over with the arm at TCP pose `here` and is resumed: its status once the
    scan has paused again, and the moves it commanded."""
    async with daemon_runner(cfg, sphere) as runner:
        await runner.recover()
        taken_over = runner.status()
        runner.arm.jog(here)
        await runner.resume()
        await until(lambda: runner.state == "paused" and runner.job.reason, "the pause")
        return taken_over, runner.status(), list(runner.arm.commanded)


async def completed(cfg, sphere, here):  # noqa: F811
    """A daemon on cfg takes the scan over with the arm at `here`, is resumed, and runs it to its end."""
    async with daemon_runner(cfg, sphere) as runner:
        await runner.recover()
        runner.arm.jog(here)
        await runner.resume()
        return await runner.wait("vase")


def test_a_restarted_daemon_whose_limits_refuse_a_pose_of_the_way_forward_moves_nothing(arun, tmp_path,
                                                                                       sphere):  # noqa: F811
    """The [arm] workspace tightened across a restart refuses pose 7, which the walk on from where a fault stopped
    the arm (between poses 2 and 3) passes: the scan pauses with the reason before the arm goes, not once it stands
    at pose 7; with the limits restored the scan completes."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = owing(arun, cfg, sphere, tmp_path)
    tight = make_cfg(tmp_path, views=VIEWS, arm={"workspace_min": [-1.0, -1.0, 0.2], "workspace_max": [1, 1, 1]})
    plan = plan_of(folder)
    check_workspace(plan[8:], tight.arm, "the rest of the plan")  # what the takeover checks passes
    assert plan[7][2, 3] < 0.2  # pose 7 does not
    here, _ = stopped_on_the_next_move(arun, cfg, sphere, 3)
    chunks = published(folder)
    taken_over, paused, moves = arun(refused_at_resume(tight, sphere, here))
    assert taken_over["state"] == "paused" and "cannot_take_over" not in taken_over, taken_over
    assert moves == []
    reason = paused["reason"]
    assert reason.startswith("scan 'vase': pose 7 of 10: TCP at [") and "m is below workspace_min 0.200 m" in reason, \
        reason
    assert "the arm is not moved (before pose 8 it walks the scan's path from pose 2 to pose 7" in reason, reason
    assert published(folder) == chunks
    assert arun(completed(cfg, sphere, here)) == {"name": "vase", "state": "complete"}
    check_capture(folder, VIEWS, 2)


def test_a_way_back_from_before_the_first_pose_owed_is_checked_against_the_limits(arun, tmp_path,
                                                                                  sphere):  # noqa: F811
    """Pose 3 owed, the arm jogged to pose 1: the way back begins there, before the poses the takeover checked
    (from pose 3), and passes pose 2, which the current limits refuse: the scan pauses before the arm goes."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = owing(arun, cfg, sphere, tmp_path, which=(3,))
    plan = plan_of(folder)
    # A y limit just inside pose 2's TCP (the sensor, 5 cm out along the flange's z, keeps it outside too).
    y_max = plan[2][1, 3] - 0.005
    tight = make_cfg(tmp_path, views=VIEWS, arm={"workspace_min": [-1.0, -1.0, -1.0],
                                                 "workspace_max": [1.0, y_max, 1.0]})
    check_workspace(plan[3:], tight.arm, "the poses from the first owed")  # what the takeover checks passes
    check_workspace(plan[1][None], tight.arm, "pose 1")  # where the arm stands passes

    taken_over, paused, moves = arun(refused_at_resume(tight, sphere, plan[1]))
    assert taken_over["poses_to_take_again"] == [3], taken_over
    assert moves == []
    reason = paused["reason"]
    assert reason.startswith("scan 'vase': pose 2 of 10: TCP at [") and f"workspace_max {y_max:.3f} m" in reason, \
        reason
    assert "it walks the scan's path from pose 1 to pose 7" in reason, reason
    assert paused["poses_to_take_again"] == [3], paused


def test_a_takeover_on_a_full_disk_lists_the_poses_owed(arun, tmp_path, sphere, monkeypatch):  # noqa: F811
    """The capture cannot be reopened (no room): the scan is taken over paused all the same, and status lists the
    poses it will take again, as every other pause does; the reason names them too."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = owing(arun, cfg, sphere, tmp_path, which=(1, 3))
    real = CaptureWriter.resume.__func__
    calls = []

    def resume(cls, path, known=None):
        calls.append(path)
        if len(calls) == 1:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(cls, path, known)

    monkeypatch.setattr(CaptureWriter, "resume", classmethod(resume))

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.recover()
            taken_over = runner.status()
            runner.arm.jog(runner.job.tcp_poses[runner.job.next_pose - 1])
            await runner.resume()  # room made meanwhile
            return taken_over, await runner.wait("vase")

    taken_over, done = arun(scenario())
    assert taken_over["state"] == "paused" and taken_over["poses_to_take_again"] == [1, 3], taken_over
    assert taken_over["reason"] == ("interrupted at pose 8/10 (daemon restarted), and disk full while reopening the "
                                    "capture: No space left on device; make room, then `spadscan ctl resume`, which "
                                    "takes pose(s) 1, 3 again first (missing from the capture)"), taken_over["reason"]
    assert done == {"name": "vase", "state": "complete"}
    check_capture(folder, VIEWS, 2)


def test_a_takeover_resumed_at_once_never_says_paused(arun, tmp_path, sphere, monkeypatch):  # noqa: F811
    """`ctl resume` right after the takeover replies 'scanning': the scan task's first step must not announce a
    pause (status 'paused' with no reason) nor record one in scan.json (a daemon dying then would take the scan over
    paused, even with auto_resume)."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    arun(interrupted(cfg, sphere))
    marked = []
    real_mark = runner_module.mark_paused
    monkeypatch.setattr(runner_module, "mark_paused", lambda path, reason, *kind: (marked.append(reason),
                                                                                   real_mark(path, reason, *kind)))

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.recover()
            runner.arm.jog(runner.job.tcp_poses[runner.job.next_pose - 1])
            states, real_set = [], runner._set_state
            runner._set_state = lambda state: (states.append(state), real_set(state))
            reply = await runner.resume()
            return reply, await runner.wait("vase"), states

    reply, done, states = arun(scenario())
    assert reply["state"] == "scanning"
    assert "paused" not in states and marked == [], (states, marked)
    assert done == {"name": "vase", "state": "complete"}
    check_capture(tmp_path / "caps" / "vase", VIEWS, 2)


def crossing_ring(real):
    """build_plan for one ring of 10 views (a regular decagon about the target's axis), visited in an order whose
    move from pose 7 to pose 8 crosses its move from pose 0 to pose 1 half way: a stop there lies on both, nearer
    pose 0 than pose 7 (a path that passes close to itself, as a nearest-neighbour tour may)."""
    def build_plan(scan, arm, **kw):
        plan = real(scan, arm, **kw)
        pos = plan.tcp_poses[:, :3, 3]
        centre = pos.mean(axis=0)
        ring = np.argsort(np.arctan2(pos[:, 1] - centre[1], pos[:, 0] - centre[0]))  # vertex k at 36k degrees on
        # 0: vertex 2, 1: vertex 7 (the diameter through vertex 2); 7 -> 8: vertices 0 -> 4, whose middle lies on it
        order = ring[[2, 7, 8, 9, 1, 3, 5, 0, 4, 6]]
        return ScanPlan(plan.sensor_poses[order], plan.tcp_poses[order], plan.description)
    return build_plan


def test_a_stop_on_the_scans_next_move_that_crosses_an_earlier_move_goes_straight_on(arun, tmp_path, sphere,
                                                                                     monkeypatch):  # noqa: F811
    """No retake: the arm stopped half way from the last published pose to the next, where that move crosses an
    earlier one of the scan's path, and the published pose nearest it is an early one (pose 0). The stop is the
    scan's own move, not the retake's way: a restarted daemon goes on to the next pose from there, instead of
    walking back to pose 0 and along the whole path again."""
    monkeypatch.setattr(runner_module, "build_plan", crossing_ring(runner_module.build_plan))
    cfg = make_cfg(tmp_path, views=VIEWS, schedule="rings", rings=1, min_elevation_deg=30.0, max_elevation_deg=30.0,
                   order="planned")
    arun(interrupted(cfg, sphere))
    here, _ = stopped_on_the_next_move(arun, cfg, sphere)
    plan = plan_of(tmp_path / "caps" / "vase")
    path = plan[:, :3, 3]
    # The stop lies on the move 0 -> 1 as on 7 -> 8, and pose 0 is the published pose nearest it.
    np.testing.assert_allclose(here[:3, 3], (path[7] + path[8]) / 2, atol=1e-9)
    assert segment_distance(path[:1], path[1:2], here[:3, 3])[0] < ON_PATH_M / 10
    assert int(np.argmin(np.linalg.norm(path[:8] - here[:3, 3], axis=1))) == 0

    _, done, moves = restarted_with_the_arm_at(arun, cfg, sphere, here)
    assert visited(plan, moves) == [8, 9]
    assert done == {"name": "vase", "state": "complete"}
    check_capture(tmp_path / "caps" / "vase", VIEWS, 2)
