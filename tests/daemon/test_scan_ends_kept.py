"""A daemon keeps the record of how each scan ended (`ScanRunner.ends`, a status each) for the newest KEPT_ENDS scans
only: a daemon that runs for months does not grow without bound. A `wait` for an older scan reads how it ended from
its folder, as for a scan that ended before the daemon started."""

from __future__ import annotations

from spadscan.daemon import runner as runner_module

from test_runner import daemon_runner, make_cfg, sphere, until  # noqa: F401  (sphere: a fixture)


def test_only_the_newest_ends_are_kept_and_an_older_one_is_read_from_its_folder(arun, tmp_path, sphere,  # noqa: F811
                                                                                 monkeypatch):
    monkeypatch.setattr(runner_module, "KEPT_ENDS", 2)
    cfg = make_cfg(tmp_path, views=2)

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.0) as runner:
            for name in ("s1", "s2", "s3"):
                await runner.start(name)
                await until(lambda: name in runner.ends, f"{name}'s end")
            kept = list(runner.ends)
            oldest = await runner.wait_end("s1")
        return kept, oldest

    kept, oldest = arun(scenario())
    assert kept == ["s2", "s3"], kept
    assert oldest.state == "complete" and oldest.status is None, "read from its folder, without a status"
