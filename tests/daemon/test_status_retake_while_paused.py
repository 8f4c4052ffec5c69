"""`ctl status` of a scan paused in the daemon's hands lists under poses_to_take_again what its resume takes again as
soon as the folder shows it (a chunk moved out during the pause), not only once the resume has reopened the capture;
where only the resume can count (a chunk changed since the daemon read it), the list is there, with the reason."""

from __future__ import annotations

import shutil

from test_runner import check_capture, daemon_runner, make_cfg, paused_after, sphere  # noqa: F401  (sphere: a fixture)


def test_a_chunk_moved_out_during_a_pause_is_listed_to_take_again_before_the_resume(arun, tmp_path,
                                                                                    sphere, reads):  # noqa: F811
    cfg = make_cfg(tmp_path, views=8)
    folder = tmp_path / "caps" / "held"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "held", runner.pause, poses=4)
            before = await runner.status_now()
            shutil.move(folder / "chunk-000001", tmp_path / "chunk-000001")
            paused = await runner.status_now()
            reply = await runner.resume()
            return before, paused, reply, await runner.wait("held")

    before, paused, reply, done = arun(scenario())
    assert "poses_to_take_again" not in before, before  # nothing owed: no key, as ever
    assert paused["state"] == "paused" and paused["poses_to_take_again"] == [1], paused
    assert "poses_to_take_again_note" not in paused, paused
    assert reply["poses_to_take_again"] == [1], reply
    assert reads == [], reads  # counted from what the daemon knows of its chunks: none read
    assert done == {"name": "held", "state": "complete"}
    check_capture(folder, 8, 2)


def test_a_chunk_changed_during_a_pause_gives_an_explicit_list_and_why_the_resume_counts_again(arun, tmp_path,
                                                                                               sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=8)
    folder = tmp_path / "caps" / "held"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "held", runner.pause, poses=4)
            meta = folder / "chunk-000002" / "meta.json"
            meta.write_bytes(meta.read_bytes())  # rewritten in place: the daemon cannot tell what it holds now
            paused = await runner.status_now()
            reply = await runner.resume()
            return paused, reply, await runner.wait("held")

    paused, reply, done = arun(scenario())
    assert paused["poses_to_take_again"] == [], paused
    assert paused["poses_to_take_again_note"].startswith("chunk-000002 changed since the daemon read it: "), paused
    assert "poses_to_take_again_note" not in reply, reply  # the resume read it again: the count is the capture's
    assert done == {"name": "held", "state": "complete"}


def test_the_newest_chunk_moved_out_during_a_pause_lowers_the_pose_and_frames_as_the_resume_does(
        arun, tmp_path, sphere, reads):  # noqa: F811
    cfg = make_cfg(tmp_path, views=8)
    folder = tmp_path / "caps" / "held"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "held", runner.pause, poses=4)
            before = await runner.status_now()
            newest = sorted(folder.glob("chunk-*"))[-1]
            shutil.move(newest, tmp_path / newest.name)
            paused = await runner.status_now()
            reply = await runner.resume()
            return before, paused, reply, await runner.wait("held")

    before, paused, reply, done = arun(scenario())
    # the resume goes on from the first pose the newest chunk held (one pose a chunk, 2 frames a pose): the paused
    # status says so before it, as the resume's own reply does
    assert (paused["pose"], paused["frames"]) == (before["pose"] - 1, before["frames"] - 2), (before, paused)
    assert paused["progress"] == f"{paused['pose']}/8", paused
    assert (paused["pose"], paused["frames"]) == (reply["pose"], reply["frames"]), (paused, reply)
    assert "poses_to_take_again" not in paused and "poses_to_take_again_note" not in paused, paused
    assert reads == [], reads
    assert done == {"name": "held", "state": "complete"}
    check_capture(folder, 8, 2)


def test_a_file_named_like_a_chunk_is_no_chunk_to_the_paused_count_as_to_the_resume(arun, tmp_path,
                                                                                    sphere, reads):  # noqa: F811
    cfg = make_cfg(tmp_path, views=8)
    folder = tmp_path / "caps" / "held"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "held", runner.pause, poses=4)
            shutil.move(folder / "chunk-000001", tmp_path / "chunk-000001")
            (folder / "chunk-000099").write_text("not a chunk: a chunk is a folder")
            paused = await runner.status_now()
            reply = await runner.resume()
            return paused, reply, await runner.wait("held")

    paused, reply, done = arun(scenario())
    # the resume lists chunks as every reader does (folders only): the paused count lists the same, and needs no
    # resume to count
    assert paused["poses_to_take_again"] == [1] and "poses_to_take_again_note" not in paused, paused
    assert reply["poses_to_take_again"] == [1], reply
    assert reads == [], reads
    assert done == {"name": "held", "state": "complete"}
