"""A scan paused for a full disk cannot record that pause on it: a daemon restarted meanwhile (kill -9) checks for
room as a resume does (`room_check.no_room`: a pose's worth of files written) and says in `status` that the disk is
full, instead of telling the operator that `spadscan ctl resume` continues the scan; a scan that was paused (by the
operator, or a fault) keeps that pause's reason beside the full disk's."""

from __future__ import annotations


import pytest

import spadscan.daemon.room_check as room_check
from spadscan.protocol.capture_format import MANIFEST, read_json
from spadscan.protocol.errors import ConfigError

from disk_faults import switchable_full_disk
from test_runner import (check_capture, daemon_runner, make_cfg, paused_after, sphere,  # noqa: F401  (a fixture)
                         until)

VIEWS = 6


def test_a_takeover_on_a_disk_with_no_room_for_a_chunk_says_so(arun, tmp_path, sphere, monkeypatch):  # noqa: F811
    """The disk takes a manifest but not a chunk (the resume's check of room fails with ENOSPC): the restarted
    daemon takes the scan over paused with the full disk as its reason; a resume is refused for it, the arm not
    moved; once room is made the scan completes, every pose once."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = tmp_path / "caps" / "full"
    full = switchable_full_disk(monkeypatch, room_check, "write_durable")

    async def first_daemon():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("full")
            await until(lambda: runner.job.next_pose >= 2, "two poses")

    async def second_daemon():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.recover()
            taken, moves = runner.status(), runner.arm.moves
            with pytest.raises(ConfigError) as refused:
                await runner.resume()
            still = runner.arm.moves
            full["on"] = False  # the operator makes room
            await runner.resume()
            return taken, moves, str(refused.value), still, await runner.wait("full")

    arun(first_daemon())
    full["on"] = True
    taken, moves, refused, still, done = arun(second_daemon())
    assert taken["state"] == "paused" and taken["scan"] == "full", taken
    at = taken["progress"]
    assert taken["reason"] == (f"interrupted at pose {at} (daemon restarted), and the captures' disk is still full "
                               f"(No space left on device: no room for the next pose's chunk in {folder}); make room "
                               f"on it, then `spadscan ctl resume`"), taken["reason"]
    assert taken["last_error"] == taken["reason"], taken
    assert refused.startswith("cannot resume scan 'full': the captures' disk is still full"), refused
    assert still == moves  # the arm stayed where it was
    assert done == {"name": "full", "state": "complete"}
    check_capture(folder, VIEWS, 2)
    assert not list(folder.glob(".tmp-*"))


@pytest.mark.parametrize("paused", [True, False])
def test_a_takeover_on_a_full_disk_keeps_the_pause_reason_the_scan_had(arun, tmp_path, sphere, monkeypatch,
                                                                     paused):  # noqa: F811
    """The operator paused the scan (or it was interrupted), then the daemon was restarted on a disk with no room for
    a chunk: the reason says the operator's pause first, then the full disk, and so does it after a resume refused for
    the disk. The capture records the pause alone: a daemon started once room is made says the pause, not a full disk
    of the past. Before: the full disk's reason replaced the operator's, and the capture recorded it."""
    cfg = make_cfg(tmp_path, views=VIEWS)
    folder = tmp_path / "caps" / "lamp"
    full = switchable_full_disk(monkeypatch, room_check, "write_durable")

    async def first_daemon():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            if paused:
                await paused_after(runner, "lamp", runner.pause, "the operator's pause")
                return
            await runner.start("lamp")
            await until(lambda: runner.job.next_pose >= 2, "two poses")

    async def second_daemon():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.recover()
            taken = runner.status()
            with pytest.raises(ConfigError):
                await runner.resume()
            return taken, runner.status()

    async def third_daemon():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.recover()
            taken = runner.status()
            await runner.resume()
            return taken, await runner.wait("lamp")

    arun(first_daemon())
    full["on"] = True
    taken, refused = arun(second_daemon())
    recorded = read_json(folder / MANIFEST)["paused"]["reason"]
    full["on"] = False  # the operator makes room
    again, done = arun(third_daemon())
    at = taken["progress"]
    first = f"paused by user; taken over at pose {at}" if paused else f"interrupted at pose {at}"
    assert taken["state"] == "paused" and taken["reason"] == (
        f"{first} (daemon restarted), and the captures' disk is still full (No space left on device: no room for the "
        f"next pose's chunk in {folder}); make room on it, then `spadscan ctl resume`"), taken["reason"]
    assert taken["last_error"] == taken["reason"], taken
    said = "paused by user" if paused else f"interrupted at pose {at} (daemon restarted)"
    assert refused["reason"] == (f"{said}; the captures' disk is still full (No space left on device: no room for the "
                                 f"next pose's chunk in {folder}); make room on it, then `spadscan ctl resume` (pose "
                                 f"{at})"), refused["reason"]
    assert recorded == said
    # The next daemon says the pause the scan had, or its own note of an interrupted scan (not the one recorded)
    assert again["state"] == "paused" and again["reason"] == (
        said if paused else f"{said}; `spadscan ctl resume` continues"), again
    assert done == {"name": "lamp", "state": "complete"}
    check_capture(folder, VIEWS, 2)
