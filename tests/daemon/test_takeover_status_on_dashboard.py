"""A scan the daemon could not take over (a damaged chunk) still says "running" in its scan.json: the dashboard, given
the daemon's own status (`spadscan ctl status`, as `spadscan dashboard` asks it), shows the scan as not taken over,
with the daemon's reason and way out, and the daemon as the daemon says it is (idle), never the scan as scanning."""

from __future__ import annotations

import asyncio
import shutil

from spadscan.commands.dashboard import daemon_status
from spadscan.daemon.app import Dispatcher
from spadscan.daemon.control import ControlServer
from spadscan.dashboard.status import Dashboard
from spadscan.protocol.capture_format import MANIFEST, read_json, write_json_atomic

from test_runner import daemon_runner, make_cfg, until, sphere  # noqa: F401  (sphere: the fixture)


async def interrupted(cfg, sphere, name: str = "vase") -> None:  # noqa: F811
    async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
        await runner.start(name)
        await until(lambda: runner.job.next_pose >= 4, "four poses")


async def seen_by_dashboards(runner, cfg, roots) -> list[dict]:
    """The status of a dashboard on each of `roots`, each asking the daemon of `runner` over its control socket as
    `spadscan dashboard` does (its `daemon_status`: the real request and reply, with the daemon's own block)."""
    async with ControlServer(cfg.socket, Dispatcher(runner, asyncio.Event(), cfg)):
        ask = daemon_status(str(cfg.socket))
        return [await asyncio.to_thread(Dashboard(root, daemon_running=lambda r: True, daemon_status=ask).status)
                for root in roots]


async def restarted(cfg, sphere, roots=()) -> tuple[dict, list[dict]]:  # noqa: F811
    async with daemon_runner(cfg, sphere) as runner:
        await runner.recover()
        return await runner.status_now(), await seen_by_dashboards(runner, cfg, roots)


def test_a_scan_the_daemon_could_not_take_over_is_shown_so_with_the_daemons_reason(arun, tmp_path,
                                                                                  sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=10)
    root = tmp_path / "caps"
    arun(interrupted(cfg, sphere))
    chunk = sorted((root / "vase").glob("chunk-*"))[-1]
    (chunk / "hists.npy").write_bytes(b"")  # torn by a power cut
    elsewhere = tmp_path / "other"  # another root, with a copy of the scan: not the daemon's
    shutil.copytree(root / "vase", elsewhere / "vase")
    own, (seen, other) = arun(restarted(cfg, sphere, (root, elsewhere)))
    assert own["state"] == "idle" and own["cannot_take_over"]["scan"] == "vase", own

    files_only = Dashboard(root, daemon_running=lambda r: True).status()
    assert files_only["scans"][0]["state"] == "running", "from scan.json alone: the defect's reading"
    (row,) = seen["scans"]
    assert row["state"] == "not_taken_over" and row["reason"] == own["cannot_take_over"]["error"], row
    assert row["reason"].startswith("cannot take over interrupted scan 'vase': "), row
    assert seen["current"]["state"] == "not_taken_over" and not seen["current"].get("frames_per_s"), seen["current"]
    assert seen["daemon_status"]["state"] == "idle" and seen["daemon_status"]["scan"] is None
    assert seen["daemon_status"]["cannot_take_over"] == own["cannot_take_over"]
    assert seen["daemon_status_note"] is None

    assert other["daemon_status"] is None and "not to this root" in other["daemon_status_note"], other
    assert other["scans"][0]["state"] == "running"  # another root's daemon says nothing of this one's scans


def test_a_scan_also_left_running_is_shown_not_taken_over_beside_the_one_the_daemon_holds(arun, tmp_path,
                                                                                         sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=10)
    root = tmp_path / "caps"
    arun(interrupted(cfg, sphere, "vase"))
    arun(interrupted(cfg, sphere, "bowl"))
    own, (seen,) = arun(restarted(cfg, sphere, (root,)))
    held, (left,) = own["scan"], own["also_interrupted"]
    assert own["state"] == "paused" and {held, left} == {"vase", "bowl"}, own

    rows = {row["name"]: row for row in seen["scans"]}
    assert rows[held]["state"] == "paused", rows[held]
    assert rows[left]["state"] == "not_taken_over", rows[left]
    assert rows[left]["reason"].startswith(f"left running by an earlier daemon; the daemon running now holds "
                                           f"{held!r} and has not taken it over: `spadscan ctl resume {left}` "), \
        rows[left]
    assert seen["daemon_status"]["also_interrupted"] == [left]


def test_a_pause_kept_out_of_scan_json_is_shown_as_the_daemon_says_it(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=10)
    root = tmp_path / "caps"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("vase")
            await until(lambda: runner.job.next_pose >= 4, "four poses")
            await runner.pause()
            await until(lambda: runner.state == "paused", "the pause")
            # (the pause is recorded in scan.json just after the state says it)
            await until(lambda: "paused" in read_json(root / "vase" / MANIFEST), "the pause's record")
            # scan.json as a full disk leaves it: the pause not recorded, the scan still 'running' there
            manifest = read_json(root / "vase" / MANIFEST)
            manifest.pop("paused")
            manifest["reason"] = None
            write_json_atomic(root / "vase" / MANIFEST, manifest)
            files_only = await asyncio.to_thread(Dashboard(root, daemon_running=lambda r: True).status)
            return await runner.status_now(), files_only, await seen_by_dashboards(runner, cfg, (root,))

    own, files_only, (seen,) = arun(scenario())
    assert own["state"] == "paused" and own["reason"], own
    assert files_only["scans"][0]["state"] == "running", "from scan.json alone"
    (row,) = seen["scans"]
    assert row["state"] == "paused" and row["reason"] == own["reason"], row
    assert seen["current"]["state"] == "paused" and not seen["current"].get("frames_per_s"), seen["current"]
