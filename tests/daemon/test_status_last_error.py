"""`ctl status` `last_error` belongs to the scan in hand: a new scan starts without an earlier scan's fault (whose
outcome stays in `last_scan`), while a scan resumed after its own fault still shows it, and what still stands (an
abort the disk could not record yet, a scan that could not be taken over: each names its scan) stays shown."""

from __future__ import annotations

from spadscan.daemon import abort_book
from spadscan.daemon.arm.sim import SimArmFaults

from test_runner import daemon_runner, make_cfg, until, sphere  # noqa: F401  (sphere: the fixture)
from test_takeover_damaged import interrupted, restarted, tear


def test_a_new_scan_does_not_show_an_earlier_scans_fault(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=8)

    async def scenario():
        async with daemon_runner(cfg, sphere, faults=SimArmFaults(protective_stop_on_moves=(4,))) as runner:
            await runner.start("first")
            await until(lambda: runner.state == "paused", "the protective stop's pause")
            fault = runner.status()["last_error"]
            resumed = await runner.resume()
            await runner.wait("first")
            ended = runner.status()
            started = await runner.start("second")
            during = runner.status()
            await runner.wait("second")
            return fault, resumed, ended, started, during, runner.status()

    fault, resumed, ended, started, during, after = arun(scenario())
    assert fault is not None and "protective stop" in fault, fault
    assert resumed["scan"] == "first" and resumed["last_error"] == fault, resumed  # its own fault, resumed
    assert ended["last_scan"] == {"name": "first", "state": "complete"} and ended["last_error"] == fault, ended
    assert started["scan"] == "second" and started["last_error"] is None, started  # `ctl scan`'s reply
    assert during["scan"] == "second" and during["last_error"] is None, during
    assert after["last_scan"] == {"name": "second", "state": "complete"} and after["last_error"] is None, after


def test_a_new_scan_keeps_showing_a_scan_that_could_not_be_taken_over(arun, tmp_path, sphere):  # noqa: F811
    cfg = make_cfg(tmp_path, views=10)
    arun(interrupted(cfg, sphere, "vase"))
    tear(tmp_path / "caps" / "vase")

    async def then(runner, status):
        started = await runner.start("fresh")
        await runner.wait("fresh")
        return status, started

    stuck, started = arun(restarted(cfg, sphere, then))
    assert stuck["cannot_take_over"]["scan"] == "vase", stuck
    assert started["last_error"] == stuck["last_error"] == stuck["cannot_take_over"]["error"], started


def test_a_new_scan_keeps_showing_an_abort_not_recorded_yet(arun, tmp_path, sphere, monkeypatch):  # noqa: F811
    """Scan 'old' was aborted, but its disk could not record it (only its scan.json is refused here): a new scan on
    another folder starts, and last_error still says where that abort stands."""
    monkeypatch.setattr(abort_book, "ABORT_RETRY_S", 3600.0)  # no retry runs by itself meanwhile
    real = abort_book._write_abort
    monkeypatch.setattr(abort_book, "_write_abort", lambda path, reason, writer: (
        "disk full while recording it" if path.name == "old" else real(path, reason, writer)))
    cfg = make_cfg(tmp_path, views=8)

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.start("old")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            aborted = await runner.abort()
            started = await runner.start("new")
            await runner.wait("new")
            return aborted, started

    aborted, started = arun(scenario())
    assert aborted["abort_recorded"] is False and aborted["last_error"].startswith("scan 'old' is aborted"), aborted
    assert started["last_error"] == aborted["last_error"] and "old" in started["unrecorded_aborts"], started


def test_a_scan_that_could_not_be_taken_over_comes_back_after_a_later_fault(arun, tmp_path, sphere):  # noqa: F811
    """A later scan's fault replaced the stuck scan's line; the next scan shows the stuck scan's line again, which
    still stands (`cannot_take_over` names it), not nothing."""
    cfg = make_cfg(tmp_path, views=10)
    arun(interrupted(cfg, sphere, "vase"))
    tear(tmp_path / "caps" / "vase")

    async def then(runner, status):
        await runner.start("first")
        await until(lambda: runner.job.next_pose >= 2, "two poses")
        runner.arm.trigger_protective_stop()
        await until(lambda: runner.state == "paused", "the protective stop's pause")
        faulted = runner.status()
        await runner.resume()
        await runner.wait("first")
        started = await runner.start("second")
        await runner.wait("second")
        return status, faulted, started

    stuck, faulted, started = arun(restarted(cfg, sphere, then))
    assert "protective stop" in faulted["last_error"]
    assert started["cannot_take_over"]["scan"] == "vase"
    assert started["last_error"] == stuck["cannot_take_over"]["error"], started["last_error"]


def test_taking_another_scan_over_by_name_does_not_show_an_earlier_scans_fault(arun, tmp_path, sphere):  # noqa: F811
    """`ctl resume other` after scan 'first' faulted and was aborted: the status of 'other' does not show the
    protective stop of 'first' as its last error."""
    cfg = make_cfg(tmp_path, views=10)
    arun(interrupted(cfg, sphere, "other"))  # left 'running' on disk, not held by the next daemon

    async def scenario():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.start("first")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            runner.arm.trigger_protective_stop()
            await until(lambda: runner.state == "paused", "the protective stop's pause")
            fault = runner.status()["last_error"]
            await runner.abort(reason="operator gave up")
            return fault, await runner.resume("other")

    fault, taken = arun(scenario())
    assert "protective stop" in fault
    assert taken["scan"] == "other" and taken["last_scan"]["name"] == "first"
    assert taken["last_error"] is None, taken["last_error"]
