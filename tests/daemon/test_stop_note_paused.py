"""The line a daemon stopped while a scan is paused logs (`scan NAME left paused at pose i/n`) gives the pose the next
daemon resumes at: counted from the scan's folder as the resume counts it, so that a chunk the operator moved out
during the pause lowers it, as `ctl status` of the paused scan does."""

from __future__ import annotations

import logging
import shutil

from spadscan.protocol.capture_writer import CaptureWriter

from test_runner import daemon_runner, make_cfg, paused_after, sphere  # noqa: F401  (sphere: a fixture)

VIEWS = 8


def test_the_paused_stop_note_counts_a_chunk_moved_out_during_the_pause(arun, tmp_path, sphere,
                                                                         caplog):  # noqa: F811
    caplog.set_level(logging.INFO, logger="spadscan.daemon")
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = tmp_path / "caps" / "held"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "held", runner.pause, poses=4)
            before = runner.status()
            newest = sorted(folder.glob("chunk-*"))[-1]
            shutil.move(newest, tmp_path / newest.name)  # the resume goes on from the first pose it held
            return before
        # (leaving daemon_runner stops the runner with the scan paused: its stop note is logged then)

    before = arun(scenario())
    on_disk = CaptureWriter.resume(folder).next_pose_index  # what the next daemon resumes at
    assert on_disk == before["pose"] - 1, (on_disk, before)
    left = [r.getMessage() for r in caplog.records if r.getMessage().startswith("scan held left")]
    assert left == [f"scan held left paused at pose {on_disk}/{VIEWS} (paused by user), resumable: start the "
                    f"daemon again, then `spadscan ctl resume`"], left
