"""A resume that comes while an abort is under way, or once it has ended the daemon's last scan, says so: the scan
is named with the abort's reason, instead of `nothing to resume (daemon is idle)` as if no scan had run. The
interleaving is forced with hooks, not timing."""

from __future__ import annotations

import asyncio

import pytest

from spadscan.daemon import abort_book
from spadscan.daemon.runner import ScanRunner
from spadscan.protocol.errors import ConfigError

from test_abort_durable import manifest
from test_abort_races import held_in_thread
from test_runner import daemon_runner, make_cfg, sphere, until  # noqa: F401  (sphere: a fixture)


async def paused_scan(runner, name: str) -> None:
    await runner.start(name)
    await until(lambda: runner.job.next_pose >= 2, "two poses")
    await runner.pause()
    await until(lambda: runner.state == "paused", "the pause")


def test_a_resume_raced_by_an_abort_names_the_abort(arun, tmp_path, sphere, monkeypatch):  # noqa: F811
    """The abort of a paused scan is being written (held on the writer thread) when `ctl resume` comes: the resume
    is refused at once, naming the scan and the abort's reason; the abort lands."""
    cfg = make_cfg(tmp_path, views=20)
    checking = asyncio.Event()  # the resume has begun its checks (the scan's capture reopened behind the abort)
    real_check = ScanRunner._check_resumable

    async def noted_check(self, job):
        checking.set()
        await real_check(self, job)

    monkeypatch.setattr(ScanRunner, "_check_resumable", noted_check)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_scan(runner, "huge2")
            writing, release = held_in_thread(monkeypatch, "_write_abort", abort_book)
            try:
                abort = asyncio.ensure_future(runner.abort("wrong object"))
                await until(writing.is_set, "the abort's write begun")
                resume = asyncio.ensure_future(runner.resume())
                await until(lambda: resume.done() or checking.is_set(), "the resume refused, or checking")
            finally:
                release.set()
            aborted, refused = await asyncio.gather(abort, resume, return_exceptions=True)
            return aborted, refused, runner.status()

    aborted, refused, status = arun(scenario())
    assert aborted["aborted"] == "huge2" and aborted["abort_recorded"] is True, aborted
    assert isinstance(refused, ConfigError), refused
    assert str(refused) == "nothing to resume: scan 'huge2' is being aborted (wrong object)", refused
    assert status["state"] == "idle" and manifest(tmp_path / "caps" / "huge2")["state"] == "aborted", status


@pytest.mark.parametrize("how", ["held", "interrupted"])
def test_a_resume_after_the_last_scan_was_aborted_names_it(arun, tmp_path, sphere, how):  # noqa: F811
    """Once the abort has ended the scan (held by the daemon, or an interrupted one it did not hold), a plain
    resume names it and the abort's reason; a later scan that completes leaves the plain refusal."""
    cfg = make_cfg(tmp_path, views=6)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            if how == "held":
                await paused_scan(runner, "huge2")
                await runner.abort("wrong object")
                return await refusals(runner)
            await runner.start("huge2")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:  # (it does not take 'huge2' over)
            await runner.abort("wrong object", name="huge2")
            return await refusals(runner)

    async def refusals(runner):
        with pytest.raises(ConfigError) as first:
            await runner.resume()
        await runner.start("next")
        await runner.wait("next")
        with pytest.raises(ConfigError) as after:
            await runner.resume()
        return str(first.value), str(after.value)

    first, after = arun(scenario())
    assert first == "nothing to resume: scan 'huge2' was aborted (wrong object); the daemon is idle", first
    assert after == "nothing to resume (daemon is idle)", after
