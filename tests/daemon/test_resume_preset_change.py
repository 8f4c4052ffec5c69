"""An interrupted scan met by a spadscan whose preset of the same name gives other numbers (an update refitted it,
the rig's config unchanged) stays blocked, and says so: which fields differ, and that only the version that started
it can finish it, never "restore it", which no key of the rig's could. What `ctl status` says of a blocked scan is
what its capture records, and so what the dashboard shows."""

from __future__ import annotations

import json

import pytest

from spadscan import __version__
from spadscan.daemon.sensor_differences import preset_changes
from spadscan.dashboard.status import Dashboard
from spadscan.protocol import sensor_presets
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import ConfigError

from test_runner import until
from test_runner_resume import a_daemon, interrupt, make_cfg, restart

PLANNED = "this spadscan's `tmf8820` preset differs from the one scan 'mix' was planned with: "
FINISH = f"finish it with spadscan {__version__}, which started it, or abort the scan (`spadscan ctl abort mix`)"


def update_preset(monkeypatch, **changes) -> None:
    """The installed spadscan's `tmf8820` preset, as an update that refitted it gives it."""
    refitted = sensor_presets.tmf8820().with_(**changes)
    monkeypatch.setitem(sensor_presets.PRESETS, "tmf8820", lambda: refitted)


def test_a_refitted_preset_names_the_field_and_the_way_out(arun, tmp_path, monkeypatch):
    arun(interrupt(make_cfg(tmp_path)))
    update_preset(monkeypatch, zero_bin=12.55)
    status, refused = arun(restart(make_cfg(tmp_path)))
    said = f"{PLANNED}zero_bin 12.4 -> 12.55; {FINISH}"
    assert status["state"] == "paused" and status["reason"] == said, status
    assert refused == f"cannot resume scan 'mix': {said}"
    assert "restore" not in refused and "[sensor] differs" not in refused
    assert CaptureReader(tmp_path / "caps" / "mix").state == "running"


def test_many_fields_are_named_a_few_then_counted(arun, tmp_path, monkeypatch):
    arun(interrupt(make_cfg(tmp_path)))
    update_preset(monkeypatch, zero_bin=12.55, crosstalk=0.03, jitter_bins=0.5, max_count=2**20, pileup=False)
    status, _ = arun(restart(make_cfg(tmp_path)))
    assert status["reason"] == (f"{PLANNED}zero_bin 12.4 -> 12.55, pileup true -> false, crosstalk 0.021 -> 0.03 "
                                f"and 2 more; {FINISH}"), status


def test_a_refit_of_the_signal_too_is_the_presets_not_the_power_keys(arun, tmp_path, monkeypatch):
    """signal_scale is also what [sensor] power sets; with no power key in the rig, and the preset's other numbers
    refitted too, its change is the preset's."""
    arun(interrupt(make_cfg(tmp_path)))
    update_preset(monkeypatch, zero_bin=12.55, signal_scale=0.3)
    status, _ = arun(restart(make_cfg(tmp_path)))
    assert status["reason"] == f"{PLANNED}zero_bin 12.4 -> 12.55, signal_scale 0.27 -> 0.3; {FINISH}", status


def test_a_changed_rig_key_and_a_refitted_preset_are_both_said(arun, tmp_path, monkeypatch):
    arun(interrupt(make_cfg(tmp_path)))
    update_preset(monkeypatch, zero_bin=12.55)
    status, refused = arun(restart(make_cfg(tmp_path, ambient=1e-4)))
    assert status["reason"] == ("the rig's [sensor] differs from the one scan 'mix' was planned with (ambient); "
                                f"{PLANNED}zero_bin 12.4 -> 12.55; restore the rig and {FINISH}"), status


def test_another_preset_chosen_in_the_rig_keeps_its_message(arun, tmp_path, monkeypatch):
    """The rig's preset changed (the operator's doing), however the installed presets changed too."""
    arun(interrupt(make_cfg(tmp_path)))
    update_preset(monkeypatch, zero_bin=12.55)
    status, _ = arun(restart(make_cfg(tmp_path, preset="lcspc-sim")))
    assert status["reason"] == ("the rig's [sensor] differs from the one scan 'mix' was planned with (preset); "
                                "restore it to resume, or abort the scan (`spadscan ctl abort mix`)"), status


def test_the_preset_put_back_resumes(arun, tmp_path, monkeypatch):
    """Back on the version that started it (the preset as planned), the scan goes on: the block the other version
    recorded in the capture is not taken for a pause."""
    arun(interrupt(make_cfg(tmp_path)))
    with monkeypatch.context() as patch:
        update_preset(patch, zero_bin=12.55)
        arun(restart(make_cfg(tmp_path)))
    assert PLANNED in CaptureReader(tmp_path / "caps" / "mix").manifest["paused"]["reason"]
    status, refused = arun(restart(make_cfg(tmp_path)))
    assert refused is None and status["reason"].startswith("interrupted at pose"), status


async def blocked_as_shown(cfg, root) -> tuple[dict, str, dict]:
    """A daemon on cfg takes the scan over blocked; (its status, the pause its capture records once the scan task
    has recorded it, the dashboard's scan in hand then)."""
    async with a_daemon(cfg) as (runner, _):
        await runner.recover()
        status = runner.status()
        manifest = lambda: CaptureReader(root / "mix").manifest  # noqa: E731
        await until(lambda: (manifest().get("paused") or {}).get("reason") == status["reason"],
                    "the block recorded in the capture")
        with pytest.raises(ConfigError):
            await runner.resume()
        return status, manifest()["paused"]["reason"], Dashboard(root).status()["current"]


def test_ctl_status_and_the_dashboard_say_the_same_of_a_blocked_scan(arun, tmp_path, monkeypatch):
    arun(interrupt(make_cfg(tmp_path)))
    update_preset(monkeypatch, zero_bin=12.55)
    status, recorded, shown = arun(blocked_as_shown(make_cfg(tmp_path), tmp_path / "caps"))
    assert status["reason"].startswith(PLANNED) and recorded == status["reason"]
    assert shown["name"] == "mix" and shown["state"] == "paused" and shown["reason"] == status["reason"], shown


def test_preset_changes_say_nested_and_long_values_shortly():
    then = sensor_presets.tmf8820().to_dict()
    now = sensor_presets.tmf8820().to_dict()
    now["zones"] = now["zones"][:4]
    now["pulse"] = {**now["pulse"], "values": [0.5] * 45, "origin": 3}
    plain = lambda record: json.loads(json.dumps(record))  # noqa: E731  (as a capture has it: lists, not tuples)
    assert preset_changes(plain(then), plain(now)) == ["zones 9 -> 4 entries", "pulse.values changed",
                                                        "pulse.origin 4 -> 3"]
    now = plain(then)
    now["zones"][4]["gain"] = 1.1
    assert preset_changes(plain(then), now) == ["zones[4].gain 1 -> 1.1"]
