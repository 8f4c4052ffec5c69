"""A resume reads again only what changed in the capture since the pause: the chunks this daemon published are known
to its writer's book (`ScanJob.chunk_book`), also once a fault has dropped the writer, so that resuming a long scan
does not read every chunk of it again. A chunk moved out meanwhile is still owed and taken again, reading no other
(test_runner_disk_room.py)."""

from __future__ import annotations

import pytest

from spadscan.daemon.arm.sim import SimArmFaults

from test_runner import check_capture, daemon_runner, make_cfg, sphere, until  # noqa: F401  (sphere: a fixture)


@pytest.mark.parametrize("paused_by", ["user", "arm fault"])
def test_a_resume_reads_no_chunk_the_daemon_published(arun, tmp_path, sphere, reads, paused_by):  # noqa: F811
    cfg = make_cfg(tmp_path, views=8)
    faults = SimArmFaults(protective_stop_on_moves=(5,) if paused_by == "arm fault" else ())

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01, faults=faults) as runner:
            await runner.start("long")
            if paused_by == "user":
                await until(lambda: runner.job.next_pose >= 4, "four poses")
                await runner.pause()
            await until(lambda: runner.state == "paused", "the pause")
            published = runner.job.next_pose
            await runner.resume()
            return published, await runner.wait("long")

    published, done = arun(scenario())
    assert published >= 4 and done == {"name": "long", "state": "complete"}
    assert reads == [], reads
    check_capture(tmp_path / "caps" / "long", 8, 2)
