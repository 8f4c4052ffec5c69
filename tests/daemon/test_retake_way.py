"""The retake's way along the scan's path (back to the poses a damaged chunk held, forward again to the last published
pose) is walked to its end whatever stops it: a pause, a fault or a daemon restarted on the way forward, once every
owed pose is taken, must not let the next run move straight from an early pose across the scan to its next pose.
While a fault has paused the scan on that way, status still lists the poses owed and the reason names where the arm
stopped. Each stop is forced at a chosen move with hooks, not timing."""

from __future__ import annotations

import asyncio
import shutil

import numpy as np
import pytest

from spadscan.daemon.arm.sim import SimArmFaults

from test_runner import check_capture, daemon_runner, make_cfg, until, sphere  # noqa: F401  (sphere: the fixture)
from test_takeover_damaged import tear

VIEWS = 10


async def interrupted(cfg, sphere):  # noqa: F811
    """Scan 'vase' cut short (as on SIGTERM) during the move to pose 8: poses 0 .. 7 published."""
    async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
        real, moving = runner.arm.move_to, asyncio.Event()

        async def move_to(tcp, speed, accel):
            if runner.job is not None and runner.job.in_flight == 8:
                moving.set()
                await asyncio.Event().wait()  # until the shutdown cancels it
            await real(tcp, speed, accel)

        runner.arm.move_to = move_to
        await runner.start("vase")
        await moving.wait()


def owing(arun, cfg, sphere, tmp_path, which=(1,)):  # noqa: F811
    """Scan 'vase' interrupted with the chunks of poses `which` moved out (damaged): their poses are owed."""
    folder = tmp_path / "caps" / "vase"
    arun(interrupted(cfg, sphere))
    assert len(list(folder.glob("chunk-*"))) == 8
    for name in [tear(folder, k) for k in which]:
        shutil.move(folder / name, tmp_path / name)
    return folder


def stop_on_the_way(runner, pose: int, how: str, owed: tuple[int, ...] = ()) -> dict:
    """As the arm is sent to `pose` on the retake's way with the poses `owed` still owed (none: on the way forward,
    every pose taken): `ctl pause` (the move is finished first) or a protective stop half way there (how: "pause",
    "fault"). Returns {"at": True} once done."""
    arm, real, done = runner.arm, runner.arm.move_to, {}
    plan = runner.job.tcp_poses.copy()

    async def move_to(tcp, speed, accel):
        still = [r.pose for r in runner.job.writer.retakes]  # (the writer is open while the arm moves)
        if not done and still == list(owed) and np.allclose(tcp, plan[pose]):
            done["at"] = True
            if how == "pause":
                await runner.pause()
            else:
                arm.faults = SimArmFaults(protective_stop_on_moves=(arm.moves + 1,))
        await real(tcp, speed, accel)

    arm.move_to = move_to
    return done


def visited(plan: np.ndarray, moves: list) -> list[int]:
    """The plan's pose each commanded move went to (every move of the daemon goes to a planned pose)."""
    out = [int(np.argmin(np.abs(plan - m).sum(axis=(1, 2)))) for m in moves]
    assert all(np.allclose(plan[v], m) for v, m in zip(out, moves)), "a move to a pose off the plan"
    return out


def nearest(plan: np.ndarray, tcp: np.ndarray, last: int) -> int:
    return int(np.argmin(np.linalg.norm(plan[:last + 1, :3, 3] - tcp[:3, 3], axis=1)))


def assert_along_the_path(start: int, poses: list[int], last: int) -> None:
    """From pose `start` (where the arm stood), each move goes to a neighbouring pose of the plan: it never crosses the
    scan; the way reaches the last published pose before the scan goes on to the next."""
    steps = [start, *poses]
    assert all(abs(b - a) <= 1 for a, b in zip(steps, steps[1:])), steps
    assert poses[-(VIEWS - last):] == list(range(last, VIEWS)), poses


def test_a_pause_on_the_way_forward_walks_on_to_the_last_published_pose_at_resume(arun, tmp_path,
                                                                                  sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = owing(arun, cfg, sphere, tmp_path)

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.recover()
            plan, last = runner.job.tcp_poses.copy(), runner.job.next_pose - 1
            runner.arm.jog(plan[last])  # where the interrupted scan left the arm
            stopped = stop_on_the_way(runner, 2, "pause")
            await runner.resume()
            await until(lambda: stopped and runner.state == "paused", "the pause on the way forward")
            here = runner.arm.actual_pose()
            status, commanded = runner.status(), len(runner.arm.commanded)
            await runner.resume()
            done = await runner.wait("vase")
            return stopped, status, plan, last, here, runner.arm.commanded[commanded:], done

    stopped, status, plan, last, here, moves, done = arun(scenario())
    assert stopped and status["reason"] == "paused by user" and "poses_to_take_again" not in status, status
    at = nearest(plan, here, last)
    assert at == 2
    assert_along_the_path(at, visited(plan, moves), last)
    assert done == {"name": "vase", "state": "complete"}
    check_capture(folder, VIEWS, 2)


def test_a_fault_on_the_way_forward_walks_on_from_where_the_arm_stopped(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = owing(arun, cfg, sphere, tmp_path)

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.recover()
            plan, last = runner.job.tcp_poses.copy(), runner.job.next_pose - 1
            runner.arm.jog(plan[last])
            stopped = stop_on_the_way(runner, 3, "fault")
            await runner.resume()
            await until(lambda: stopped and runner.state == "paused", "the fault's pause")
            here = runner.arm.actual_pose()
            status, commanded = runner.status(), len(runner.arm.commanded)
            await runner.resume()
            done = await runner.wait("vase")
            return status, plan, last, here, runner.arm.commanded[commanded:], done

    status, plan, last, here, moves, done = arun(scenario())
    halfway = (plan[2][:3, 3] + plan[3][:3, 3]) / 2
    np.testing.assert_allclose(here[:3, 3], halfway, atol=1e-9)  # the sim's protective stop: half way
    assert_along_the_path(nearest(plan, here, last), visited(plan, moves), last)
    assert status["reason"].endswith(f"(the arm was moving to pose 3, on its way forward along the scan's path to "
                                     f"pose {last}, the last published; the scan goes on at pose {last + 1}/"
                                     f"{VIEWS})"), status["reason"]
    assert done == {"name": "vase", "state": "complete"}
    check_capture(folder, VIEWS, 2)


@pytest.mark.parametrize("how", ["pause", "fault"])
def test_a_daemon_restarted_on_the_way_forward_walks_on_from_where_the_arm_stands(arun, tmp_path, sphere,  # noqa: F811
                                                                                  how):
    """No record says the way was unfinished: the restarted daemon finds the arm on the scan's path before its last
    published pose (at a pose after a pause; between two after a protective stop) and walks on from there."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = owing(arun, cfg, sphere, tmp_path)

    async def first():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.recover()
            runner.arm.jog(runner.job.tcp_poses[runner.job.next_pose - 1])
            stopped = stop_on_the_way(runner, 3, how)
            await runner.resume()
            await until(lambda: stopped and runner.state == "paused", "the stop on the way forward")
            return runner.arm.actual_pose()

    async def restarted(here):
        async with daemon_runner(cfg, sphere) as runner:
            await runner.recover()
            plan, last = runner.job.tcp_poses.copy(), runner.job.next_pose - 1
            runner.arm.jog(here)  # the arm stands where the stopped daemon left it
            status = runner.status()
            await runner.resume()
            done = await runner.wait("vase")
            return status, plan, last, runner.arm.commanded, done

    here = arun(first())
    status, plan, last, moves, done = arun(restarted(here))
    assert status["state"] == "paused" and "poses_to_take_again" not in status, status
    at = nearest(plan, here, last)
    assert at == 3 if how == "pause" else at in (2, 3)
    assert_along_the_path(at, visited(plan, moves), last)
    assert done == {"name": "vase", "state": "complete"}
    check_capture(folder, VIEWS, 2)


def test_a_fault_on_the_way_back_keeps_the_poses_owed_in_status_and_names_where_the_arm_stopped(arun, tmp_path,
                                                                                              sphere):  # noqa: F811
    """examples/README.md: status lists them under poses_to_take_again until they are published; the fault's reason
    names the pose of the way, where the operator at the pendant finds the arm, not the scan's next pose."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = owing(arun, cfg, sphere, tmp_path, which=(1, 3))

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.recover()
            taken_over = runner.status()
            runner.arm.jog(runner.job.tcp_poses[runner.job.next_pose - 1])
            # pose 3 is taken again on the way back, pose 1 not yet
            stopped = stop_on_the_way(runner, 2, "fault", owed=(1,))
            await runner.resume()
            await until(lambda: stopped and runner.state == "paused", "the fault's pause")
            paused = runner.status()
            await runner.resume()
            return taken_over, paused, await runner.wait("vase")

    taken_over, paused, done = arun(scenario())
    assert taken_over["poses_to_take_again"] == [1, 3], taken_over
    assert paused["poses_to_take_again"] == [1], paused
    assert paused["reason"].startswith("arm fault: arm (sim): protective stop during move "), paused["reason"]
    assert paused["reason"].endswith("then resume (the arm was moving to pose 2, on its way back along the scan's "
                                     "path to take pose(s) 1 again; the scan goes on at pose 8/10)"), paused["reason"]
    assert done == {"name": "vase", "state": "complete"}
    check_capture(folder, VIEWS, 2)


def stopped_on_the_next_move(arun, cfg, sphere, pose: int = 8) -> tuple[np.ndarray, str]:  # noqa: F811
    """A daemon takes the interrupted scan over with the arm at its last published pose, and a fault stops the arm
    half way to `pose` (by default the next, pose 8; an earlier one: on the way back to the poses owed): (where the
    arm stopped, the pause's reason)."""
    async def first():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.recover()
            runner.arm.jog(runner.job.tcp_poses[runner.job.next_pose - 1])
            stopped = stop_on_the_way(runner, pose, "fault")
            await runner.resume()
            await until(lambda: stopped and runner.state == "paused", "the fault's pause")
            return runner.arm.actual_pose(), runner.status()["reason"]

    return arun(first())


def restarted_with_the_arm_at(arun, cfg, sphere, here: np.ndarray) -> tuple[np.ndarray, dict, list]:  # noqa: F811
    """A restarted daemon finds the arm at `here` and resumes the scan to its end: (the plan, the scan's end, the
    moves it commanded)."""
    async def restarted():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.recover()
            runner.arm.jog(here)
            await runner.resume()
            return runner.job.tcp_poses.copy(), await runner.wait("vase"), runner.arm.commanded

    return arun(restarted())


def test_a_daemon_restarted_with_the_arm_stopped_on_the_scans_next_move_goes_straight_on(arun, tmp_path,
                                                                                         sphere):  # noqa: F811
    """No retake: a stop between the last published pose and the next leaves the arm on the plan's own move, and a
    restarted daemon goes on to the next pose from there (no walk back along the path)."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    arun(interrupted(cfg, sphere))
    here, reason = stopped_on_the_next_move(arun, cfg, sphere)
    plan, done, moves = restarted_with_the_arm_at(arun, cfg, sphere, here)
    assert reason.endswith("(pose 8/10)"), reason
    assert visited(plan, moves) == [8, 9]
    assert done == {"name": "vase", "state": "complete"}
    check_capture(tmp_path / "caps" / "vase", VIEWS, 2)
