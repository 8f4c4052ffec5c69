"""A scan the daemon could not take over (a damaged chunk) still says "running" in its scan.json: the dashboard, given
the daemon's own status (`spadscan ctl status`, as `spadscan dashboard` asks it), shows the scan as not taken over,
with the daemon's reason and way out, and the daemon as the daemon says it is (idle), never the scan as scanning."""

from __future__ import annotations

from spadscan.dashboard.status import Dashboard

from test_runner import daemon_runner, make_cfg, until, sphere  # noqa: F401  (sphere: the fixture)


async def interrupted(cfg, sphere) -> None:  # noqa: F811
    async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
        await runner.start("vase")
        await until(lambda: runner.job.next_pose >= 4, "four poses")


async def restarted(cfg, sphere) -> dict:  # noqa: F811
    async with daemon_runner(cfg, sphere) as runner:
        await runner.recover()
        return await runner.status_now()


def test_a_scan_the_daemon_could_not_take_over_is_shown_so_with_the_daemons_reason(arun, tmp_path,
                                                                                  sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=10)
    root = tmp_path / "caps"
    arun(interrupted(cfg, sphere))
    chunk = sorted((root / "vase").glob("chunk-*"))[-1]
    (chunk / "hists.npy").write_bytes(b"")  # torn by a power cut
    own = arun(restarted(cfg, sphere))
    assert own["state"] == "idle" and own["cannot_take_over"]["scan"] == "vase", own
    reply = {**own, "ok": True, "daemon": {"captures": str(root)}}

    files_only = Dashboard(root, daemon_running=lambda r: True).status()
    assert files_only["scans"][0]["state"] == "running", "from scan.json alone: the defect's reading"
    seen = Dashboard(root, daemon_running=lambda r: True, daemon_status=lambda r: reply).status()
    (row,) = seen["scans"]
    assert row["state"] == "not_taken_over" and row["reason"] == own["cannot_take_over"]["error"], row
    assert row["reason"].startswith("cannot take over interrupted scan 'vase': "), row
    assert seen["current"]["state"] == "not_taken_over" and not seen["current"].get("frames_per_s"), seen["current"]
    assert seen["daemon_status"]["state"] == "idle" and seen["daemon_status"]["scan"] is None
    assert seen["daemon_status"]["cannot_take_over"] == own["cannot_take_over"]
    assert seen["daemon_status_note"] is None

    elsewhere = {**reply, "daemon": {"captures": str(tmp_path / "other")}}
    other = Dashboard(root, daemon_running=lambda r: True, daemon_status=lambda r: elsewhere).status()
    assert other["daemon_status"] is None and "not to this root" in other["daemon_status_note"], other
    assert other["scans"][0]["state"] == "running"  # another root's daemon says nothing of this one's scans
