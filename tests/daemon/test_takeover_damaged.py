"""An interrupted scan with a damaged chunk (a file torn or zeroed by a power cut) is never stuck for good: the
takeover's one-line error names the chunk and the ways out. `ctl abort NAME` ends the scan as aborted with every
chunk kept; moving the chunk out of the folder and `ctl resume` takes the scan over and finishes it."""

from __future__ import annotations

import builtins
import errno
import os
import shutil

import numpy as np
import pytest

from spadscan.daemon.scan_job import way_out
from spadscan.protocol import capture_format
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import ConfigError

from test_runner import check_capture, daemon_runner, make_cfg, until, sphere  # noqa: F401  (sphere: the fixture)

VIEWS = 10


async def interrupted(cfg, sphere, name: str = "vase") -> None:  # noqa: F811
    """Scan `name` is cut short (as on SIGTERM) with a few poses published."""
    async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
        await runner.start(name)
        await until(lambda: runner.job.next_pose >= 4, "four poses")


def tear(folder, which: int = -1) -> str:
    """Zero one chunk's hists.npy (a power cut); returns the chunk's name."""
    chunk = sorted(folder.glob("chunk-*"))[which]
    (chunk / "hists.npy").write_bytes(b"")
    return chunk.name


async def restarted(cfg, sphere, then) -> object:  # noqa: F811
    """A daemon on cfg recovers; `then(runner, status)` runs before it stops and its result is returned."""
    async with daemon_runner(cfg, sphere) as runner:
        await runner.recover()
        return await then(runner, runner.status())


def test_a_scan_with_a_damaged_chunk_says_the_way_out_and_can_be_aborted_keeping_every_chunk(arun, tmp_path,
                                                                                              sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=VIEWS, auto_resume=True)
    folder = tmp_path / "caps" / "vase"
    arun(interrupted(cfg, sphere))
    damaged = tear(folder)
    kept = {p.relative_to(folder): p.read_bytes() for p in folder.glob("chunk-*/*")}

    async def then(runner, status):
        with pytest.raises(ConfigError) as unnamed:
            await runner.abort()
        return status, str(unnamed.value), await runner.abort(name="vase"), runner.status()

    status, unnamed, reply, after = arun(restarted(cfg, sphere, then))
    said = status["last_error"]
    assert status["state"] == "idle" and status["cannot_take_over"]["scan"] == "vase", status
    assert said.startswith("cannot take over interrupted scan 'vase': ") and "\n" not in said, said
    assert f"{damaged} cannot be read: move it out of {folder} (its poses are taken again), then " \
           f"`spadscan ctl resume vase`; or `spadscan ctl abort vase` ends the scan as aborted, keeping every " \
           f"chunk" in said, said
    assert unnamed == ("nothing to abort (daemon is idle); scan 'vase' could not be taken over: "
                       "`spadscan ctl abort vase` ends it"), unnamed
    assert reply["aborted"] == "vase" and reply["abort_recorded"] is True, reply
    assert after["last_error"] is None and "cannot_take_over" not in after
    assert after["last_scan"] == {"name": "vase", "state": "aborted"}
    manifest = CaptureReader(folder).manifest
    assert manifest["state"] == "aborted" and manifest["reason"].startswith(
        "aborted by user; it could not be taken over: ") and damaged in manifest["reason"], manifest["reason"]
    assert {p.relative_to(folder): p.read_bytes() for p in folder.glob("chunk-*/*")} == kept  # nothing removed


def test_a_damaged_last_chunk_moved_out_lets_ctl_resume_finish_the_scan(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = tmp_path / "caps" / "vase"
    arun(interrupted(cfg, sphere))
    damaged = tear(folder)

    async def then(runner, status):
        with pytest.raises(ConfigError) as still:
            await runner.resume("vase")  # not moved out yet: refused again, with the way out
        shutil.move(folder / damaged, tmp_path / damaged)
        resumed = await runner.resume()  # the daemon holds no scan: the one it could not take over is tried again
        return str(still.value), resumed, await runner.wait("vase")

    still, resumed, done = arun(restarted(cfg, sphere, then))
    assert f"{damaged} cannot be read: move it out" in still, still
    assert resumed["state"] == "scanning" and resumed["scan"] == "vase" and "cannot_take_over" not in resumed
    assert done == {"name": "vase", "state": "complete"}
    check_capture(folder, VIEWS, 2)  # every pose once: the damaged chunk's poses were taken again
    assert (tmp_path / damaged / "meta.json").is_file()  # the operator's copy is untouched


@pytest.mark.parametrize("which", [[1], [0, 2]])
def test_damaged_chunks_before_the_last_moved_out_have_their_poses_taken_again_in_order(arun, tmp_path, sphere,
                                                                                       which):  # noqa: F811
    """The capture ends complete with every pose 0 .. P - 1 once, in pose order in its chunks' name order (the
    format's promise), the poses taken again published under the numbers moved out; the arm gets there back along
    the scan's own path (moves are straight lines: one across the scan would cross the object)."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = tmp_path / "caps" / "vase"
    arun(interrupted(cfg, sphere))
    damaged = [tear(folder, k) for k in which]
    said = way_out(folder)
    assert said.startswith(f"{', '.join(damaged)} cannot be read: move {'it' if len(damaged) == 1 else 'them'} out "
                           f"of {folder} ({'its' if len(damaged) == 1 else 'their'} poses are taken again), then "
                           f"`spadscan ctl resume vase`"), said
    for name in damaged:
        shutil.move(folder / name, tmp_path / name)

    async def then(runner, status):
        plan, last = runner.job.tcp_poses.copy(), runner.job.next_pose - 1
        await runner.arm.move_to(plan[last], 0.1, 0.5)  # where the scan left the arm (the sim arm starts at home)
        commanded = len(runner.arm.commanded)
        await runner.resume()
        done = await runner.wait("vase")
        return status, done, plan, last, runner.arm.commanded[commanded:]

    status, done, plan, last, moves = arun(restarted(cfg, sphere, then))
    assert status["poses_to_take_again"] == which and "taking pose(s) " in status["reason"], status
    assert done == {"name": "vase", "state": "complete"}
    data = check_capture(folder, VIEWS, 2)
    assert data.pose_indices.tolist() == sorted(data.pose_indices.tolist())  # in name order: pose order
    assert {f"chunk-{k:06d}" for k in which} <= {p.name for p in folder.glob("chunk-*")}
    visited = [int(np.argmin(np.abs(plan - m).sum(axis=(1, 2)))) for m in moves]
    assert all(np.allclose(plan[v], m) for v, m in zip(visited, moves)), "a move to a pose off the plan"
    low = min(which)
    back = list(range(last, low, -1)) + list(range(low, VIEWS))  # back along the path, then on to the end
    assert visited == back, visited


def test_abort_name_refuses_a_scan_that_is_not_the_daemons_to_end(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=VIEWS)
    arun(interrupted(cfg, sphere))

    async def then(runner, status):
        errors = []
        for name in ("nope", "../x"):
            with pytest.raises(ConfigError) as refused:
                await runner.abort(name=name)
            errors.append(str(refused.value))
        await runner.abort(name="vase")  # the interrupted scan it took over, paused: aborted as usual
        with pytest.raises(ConfigError) as again:
            await runner.abort(name="vase")
        return errors, str(again.value)

    errors, again = arun(restarted(cfg, sphere, then))
    assert errors[0].startswith("no scan named 'nope'") and "must be" in errors[1], errors
    assert again == "scan 'vase' has already ended (aborted)", again


def test_resume_and_abort_of_a_name_no_scan_can_have_say_why(arun, tmp_path, sphere):  # noqa: F811
    """A name too long for a file, with a NUL or a lone surrogate was looked up on disk after its refusal, and the
    lookup's own error replaced it: "internal error: OSError: [Errno 36] File name too long"."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    arun(interrupted(cfg, sphere))

    async def then(runner, status):
        await runner.abort(name="vase")  # the scan it took over at start-up: it holds none now
        said = []
        for name in ("a" * 300, "a\x00b", "\ud800"):
            for ask in (runner.resume, runner.abort):
                with pytest.raises(ConfigError) as refused:
                    await ask(name=name)
                said.append(str(refused.value))
        return said

    for line in arun(restarted(cfg, sphere, then)):
        assert line.startswith("scan name ") and "must be 1-100 letters" in line, line


def test_wait_on_an_interrupted_scan_the_daemon_does_not_hold_says_so_with_the_ways_out(arun, tmp_path,
                                                                                         sphere):  # noqa: F811
    """Not "no scan named": the scan is there, and `ctl wait` would otherwise be the operator's only word on it."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    arun(interrupted(cfg, sphere, "older"))
    arun(interrupted(cfg, sphere, "vase"))
    damaged = tear(tmp_path / "caps" / "vase")  # the latest: the one a restart tries to take over

    async def then(runner, status):
        said = []
        for name in ("vase", "older", "nope"):
            with pytest.raises(ConfigError) as refused:
                await runner.wait(name)
            said.append(str(refused.value))
        return status, said

    status, (stuck, older, nope) = arun(restarted(cfg, sphere, then))
    assert stuck == ("scan 'vase' is interrupted and not held by this daemon, so it neither ends nor goes on by "
                     "itself: " + status["cannot_take_over"]["error"]), stuck
    assert f"{damaged} cannot be read" in stuck and "`spadscan ctl abort vase`" in stuck
    assert older == ("scan 'older' is interrupted and not held by this daemon, so it neither ends nor goes on by "
                     "itself: `spadscan ctl resume older` takes it over and continues it; or `spadscan ctl abort "
                     "older` ends it as aborted, keeping every chunk"), older
    assert nope.startswith("no scan named 'nope' is running or finished in "), nope


def test_a_chunk_this_user_may_not_read_is_never_called_damaged_and_is_kept_in_place(arun, tmp_path, sphere,
                                                                                    monkeypatch):  # noqa: F811
    """A chunk made or copied by another user (its owner or mode, not its content): the way out says permission
    denied and to give read access, never to move it out (which would throw good data away); once readable, `ctl
    resume NAME` finishes the scan with every chunk where it was."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = tmp_path / "caps" / "vase"
    arun(interrupted(cfg, sphere))
    chunk = sorted(folder.glob("chunk-*"))[1]
    kept = {p.relative_to(folder): p.read_bytes() for p in chunk.glob("*")}
    denied = chunk / "hists.npy"

    def guarded_open(file, *args, **kwargs):  # as root, chmod 000 would not stop a read: refuse it at the open
        if os.fspath(file) == os.fspath(denied):
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(file))
        return builtins.open(file, *args, **kwargs)

    monkeypatch.setattr(capture_format, "open", guarded_open, raising=False)
    said = way_out(folder)
    assert said.startswith(f"{chunk.name} cannot be read by this user (permission denied): give the daemon's user "
                           f"read access"), said
    assert "move" not in said and said.endswith("`spadscan ctl abort vase` ends the scan as aborted, keeping every "
                                                "chunk"), said

    async def then(runner, status):
        with pytest.raises(ConfigError) as still:
            await runner.resume("vase")
        monkeypatch.undo()  # the operator gives read access
        resumed = await runner.resume("vase")
        return str(still.value), resumed, await runner.wait("vase")

    still, resumed, done = arun(restarted(cfg, sphere, then))
    assert "permission denied" in still and "move it out" not in still and "\n" not in still, still
    assert resumed["scan"] == "vase" and done == {"name": "vase", "state": "complete"}
    check_capture(folder, VIEWS, 2)
    assert {p.relative_to(folder): p.read_bytes() for p in chunk.glob("*")} == kept  # the chunk stayed, untouched


def test_an_older_interrupted_scan_stays_named_beside_the_one_taken_over(arun, tmp_path, sphere, caplog):  # noqa: F811
    """Scan 'old' could not be taken over (a torn chunk), the operator started 'new', and the daemon crashed: the next
    daemon takes 'new' over and names 'old' too (status and its log), until 'old' is ended by name."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    arun(interrupted(cfg, sphere, "old"))
    tear(tmp_path / "caps" / "old")
    arun(interrupted(cfg, sphere, "new"))

    async def then(runner, status):
        await runner.abort(name="old")
        return status, runner.status()

    status, after = arun(restarted(cfg, sphere, then))
    assert status["scan"] == "new" and status["state"] == "paused", status
    assert status["also_interrupted"] == ["old"], status
    assert "also left 'running' by an earlier daemon, not taken over: old" in caplog.text
    assert "also_interrupted" not in after and after["scan"] == "new", after


def test_scans_that_cannot_be_taken_over_stay_named_until_they_are_ended(arun, tmp_path, sphere):  # noqa: F811
    """Two damaged scans: one named as not taken over, the other beside it; a failed `ctl resume` of the other makes
    it the one named, and keeps the first named too. A scan moved out of the root by hand is named no more."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    for name in ("a", "b"):
        arun(interrupted(cfg, sphere, name))
        tear(tmp_path / "caps" / name)

    async def then(runner, status):
        with pytest.raises(ConfigError):
            await runner.resume(name="a")
        after = runner.status()
        (tmp_path / "caps" / "b").rename(tmp_path / "b-moved-out")
        with pytest.raises(ConfigError, match="no scan named 'b'"):
            await runner.abort(name="b")
        return status, after, runner.status()

    status, after, moved = arun(restarted(cfg, sphere, then))
    assert status["cannot_take_over"]["scan"] == "b" and status["also_interrupted"] == ["a"], status
    assert after["cannot_take_over"]["scan"] == "a" and after["also_interrupted"] == ["b"], after
    assert moved["cannot_take_over"]["scan"] == "a" and "also_interrupted" not in moved, moved
