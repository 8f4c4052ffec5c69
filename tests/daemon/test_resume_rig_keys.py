"""A resumed scan tells a changed [sensor] key from a preset an update refitted by the keys its capture records (the
sim's power, ambient and cycles, in the rig record), and names the spadscan version that started it. A real
sensor's histograms do not depend on the preset's numbers, so there a refitted preset is a note, not a block: the
scan goes on with the model its capture records."""

from __future__ import annotations

import json

import pytest

from spadscan import __version__
from spadscan.daemon import scan_job
from spadscan.daemon.app import DeviceSession
from spadscan.daemon.rig import build_devices, rig_record
from spadscan.daemon.runner import ScanRunner
from spadscan.daemon.scan_job import load_job
from spadscan.protocol import sensor_presets
from spadscan.protocol.capture_format import MANIFEST
from spadscan.protocol.capture_reader import CaptureReader

from test_runner import until
from test_runner_resume import interrupt, make_cfg, restart

PLANNED = "this spadscan's `tmf8820` preset differs from the one scan 'mix' was planned with: "
ABORT = "or abort the scan (`spadscan ctl abort mix`)"
FINISH = f"finish it with spadscan {__version__}, which started it, {ABORT}"
POWER = "the rig's [sensor] differs from the one scan 'mix' was planned with (power)"
I2C = {"backend": "i2c", "preset": "tmf8820", "bus": 1, "address": 0x41}
"""The rig record of an I2C sensor (`rig_record`): no key of its sets the model."""
SERIAL = {"backend": "serial", "preset": "tmf8820", "port": "/dev/ttyACM0", "baud": 1_000_000}
"""The rig record of a sensor behind the serial bridge."""


def update_preset(monkeypatch, **changes) -> None:
    """The installed spadscan's `tmf8820` preset, as an update that refitted it gives it."""
    refitted = sensor_presets.tmf8820().with_(**changes)
    monkeypatch.setitem(sensor_presets.PRESETS, "tmf8820", lambda: refitted)


def edit_manifest(folder, change) -> None:
    """Rewrite scan.json with `change(manifest)` applied (a capture an older spadscan started, another rig's)."""
    path = folder / MANIFEST
    manifest = json.loads(path.read_text())
    change(manifest)
    path.write_text(json.dumps(manifest))


def test_the_rig_record_holds_the_model_keys_and_the_version(arun, tmp_path):
    arun(interrupt(make_cfg(tmp_path, power=2.0, cycles=1000)))
    rig = CaptureReader(tmp_path / "caps" / "mix").manifest["rig"]
    assert rig["spadscan_version"] == __version__
    assert {k: rig["sensor"][k] for k in ("power", "ambient", "cycles")} == {"power": 2.0, "ambient": None,
                                                                            "cycles": 1000}


@pytest.mark.parametrize("field, value, said", [("signal_scale", 0.3, "signal_scale 0.27 -> 0.3"),
                                                ("background", 4e-5, "background 3e-05 -> 4e-05"),
                                                ("cycles", 5_000_000, "cycles 4000000 -> 5000000")])
def test_a_refit_of_a_keyed_field_alone_is_the_presets(arun, tmp_path, monkeypatch, field, value, said):
    """The config never changed: the key is not blamed (before: "... (power); restore it to resume")."""
    arun(interrupt(make_cfg(tmp_path)))
    update_preset(monkeypatch, **{field: value})
    status, refused = arun(restart(make_cfg(tmp_path)))
    assert status["reason"] == f"{PLANNED}{said}; {FINISH}", status
    assert refused == f"cannot resume scan 'mix': {status['reason']}"


def test_a_power_kept_while_the_preset_refits_the_signal_is_not_blamed(arun, tmp_path, monkeypatch):
    """power multiplies the preset's signal_scale: with power = 2 on both sides, 0.54 -> 0.6 is the preset's 0.27 ->
    0.3, said as the preset's values."""
    arun(interrupt(make_cfg(tmp_path, power=2.0)))
    update_preset(monkeypatch, zero_bin=12.55, signal_scale=0.3)
    status, _ = arun(restart(make_cfg(tmp_path, power=2.0)))
    assert status["reason"] == f"{PLANNED}zero_bin 12.4 -> 12.55, signal_scale 0.27 -> 0.3; {FINISH}", status


@pytest.mark.parametrize("refit, said", [({}, ""), ({"signal_scale": 0.3}, ", signal_scale 0.27 -> 0.3")])
def test_a_removed_power_key_is_named_and_the_preset_apart(arun, tmp_path, monkeypatch, refit, said):
    """power 2 -> unset is the rig's change (before: the preset's, "signal_scale 0.54 -> 0.27")."""
    arun(interrupt(make_cfg(tmp_path, power=2.0)))
    update_preset(monkeypatch, zero_bin=12.55, **refit)
    status, _ = arun(restart(make_cfg(tmp_path)))
    assert status["reason"] == (f"{POWER}; {PLANNED}zero_bin 12.4 -> 12.55{said}; restore the rig and {FINISH}"), status


def test_a_changed_key_with_the_preset_as_it_was_names_the_key_alone(arun, tmp_path):
    arun(interrupt(make_cfg(tmp_path, power=2.0, ambient=1e-4)))
    status, _ = arun(restart(make_cfg(tmp_path, power=3.0, ambient=1e-4)))
    assert status["reason"] == f"{POWER}; restore it to resume, {ABORT}", status


def without_model_keys(manifest) -> None:
    """A capture an older spadscan started: no model keys, no version in its rig record."""
    for key in ("power", "ambient", "cycles"):
        del manifest["rig"]["sensor"][key]
    del manifest["rig"]["spadscan_version"]


def test_a_capture_without_the_keys_is_inferred_from_as_before(arun, tmp_path, monkeypatch):
    """No key recorded: a keyed field alone cannot be told from the key's change, so the key is named."""
    arun(interrupt(make_cfg(tmp_path)))
    edit_manifest(tmp_path / "caps" / "mix", without_model_keys)
    update_preset(monkeypatch, signal_scale=0.3)
    status, _ = arun(restart(make_cfg(tmp_path)))
    assert status["reason"] == f"{POWER}; restore it to resume, {ABORT}", status


def test_without_the_keys_a_kept_power_divides_the_signal_before_it_is_compared(arun, tmp_path, monkeypatch):
    """The preset seen refitted (zero_bin) and signal_scale / power the installed preset's own: the preset's (before:
    power was blamed, its signal_scale 0.6 not being the preset's 0.3). A capture without the version names when it
    began instead."""
    arun(interrupt(make_cfg(tmp_path, power=2.0)))
    folder = tmp_path / "caps" / "mix"
    edit_manifest(folder, without_model_keys)
    created = CaptureReader(folder).manifest["created_utc"]
    update_preset(monkeypatch, zero_bin=12.55, signal_scale=0.3)
    status, _ = arun(restart(make_cfg(tmp_path, power=2.0)))
    day = f"{created[:10]} {created[11:16]} UTC"
    assert status["reason"] == (f"{PLANNED}zero_bin 12.4 -> 12.55, signal_scale 0.54 -> 0.6; finish it with the "
                                f"spadscan version installed on {day}, {ABORT}"), status


def test_a_capture_that_says_neither_version_nor_start_keeps_the_general_advice(arun, tmp_path, monkeypatch):
    arun(interrupt(make_cfg(tmp_path)))
    edit_manifest(tmp_path / "caps" / "mix", lambda m: (without_model_keys(m), m.pop("created_utc")))
    update_preset(monkeypatch, zero_bin=12.55)
    status, _ = arun(restart(make_cfg(tmp_path)))
    assert status["reason"] == (f"{PLANNED}zero_bin 12.4 -> 12.55; finish it with the spadscan version that started "
                                f"it, {ABORT}"), status


# ---- a real sensor: the preset does not shape its histograms -----------------------------------------------------
async def on_real(cfg, record, body):
    """A daemon whose rig records a real sensor (`record`; the devices are the sim's: only the records are compared);
    returns `body(runner)`."""
    arm, sensor = build_devices(cfg)
    async with DeviceSession([arm, sensor]):
        rig, _ = rig_record(cfg)
        runner = ScanRunner(arm, sensor, cfg, rig={**rig, "sensor": record}, scene={})
        try:
            return await body(runner)
        finally:
            await runner.shutdown()


async def started(runner):
    await runner.start("mix")
    await until(lambda: runner.job.next_pose >= 3, "three poses")


async def taken_over_and_finished(runner):
    await runner.recover()
    status = runner.status()
    await runner.resume()
    return status, await runner.wait("mix")


@pytest.mark.parametrize("record", [I2C, SERIAL], ids=["i2c", "serial"])
def test_a_refitted_preset_on_a_real_sensor_is_a_note_and_the_capture_keeps_its_model(arun, tmp_path, monkeypatch,
                                                                                      caplog, record):
    """The driver checks only the zone and bin counts against the model, and a resumed capture keeps the model it
    records: the scan goes on (before: blocked), the difference logged once and shown in `ctl status`."""
    arun(on_real(make_cfg(tmp_path), record, started))
    update_preset(monkeypatch, zero_bin=12.55, signal_scale=0.3)
    with caplog.at_level("WARNING", logger="spadscan.daemon"):
        status, end = arun(on_real(make_cfg(tmp_path), record, taken_over_and_finished))
    note = (f"{PLANNED}zero_bin 12.4 -> 12.55, signal_scale 0.27 -> 0.3; the scan goes on with the sensor model its "
            f"capture records ([sensor] backend {record['backend']!r}: the sensor's histograms do not depend on it)")
    assert status["state"] == "paused" and status["preset_note"] == note, status
    assert status["reason"].startswith("interrupted at pose"), status
    assert end == {"name": "mix", "state": "complete"}
    reader = CaptureReader(tmp_path / "caps" / "mix")
    assert reader.state == "complete" and reader.sensor.zero_bin == 12.4  # one model for every frame
    assert [r.getMessage() for r in caplog.records if "preset differs" in r.getMessage()] == [f"scan mix: {note}"]


@pytest.mark.parametrize("refit", [lambda preset: {"n_bins": 64, "zero_bin": 6.0, "ignore_bins": ()},
                                   lambda preset: {"zones": preset.zones[:4]}], ids=["bins", "zones"])
def test_on_a_real_sensor_changed_zone_or_bin_counts_still_block(arun, tmp_path, refit):
    arun(interrupt(make_cfg(tmp_path)))
    folder = tmp_path / "caps" / "mix"
    edit_manifest(folder, lambda m: (m["rig"].update(sensor=I2C), m.update(scene={})))
    preset = sensor_presets.tmf8820()
    now = preset.with_(**refit(preset))
    job = load_job(folder, make_cfg(tmp_path).arm.hand_eye, sensor_now=now, rig_now={"sensor": I2C}, scene_now={})
    assert job.blocked is not None and job.blocked.startswith(PLANNED) and job.preset_note is None, job.blocked


def test_on_a_real_sensor_another_preset_name_still_blocks(arun, tmp_path):
    arun(interrupt(make_cfg(tmp_path)))
    folder = tmp_path / "caps" / "mix"
    edit_manifest(folder, lambda m: (m["rig"].update(sensor=I2C), m.update(scene={})))
    now = sensor_presets.sensor_preset("lcspc-sim")
    job = load_job(folder, make_cfg(tmp_path).arm.hand_eye, sensor_now=now, rig_now={"sensor": I2C}, scene_now={})
    assert job.blocked == (f"the rig's [sensor] differs from the one scan 'mix' was planned with (preset); restore it "
                           f"to resume, {ABORT}") and job.preset_note is None


def test_on_the_sim_a_refitted_preset_still_blocks(arun, tmp_path, monkeypatch):
    """The sim renders with the model: a resume would take the rest of the scan with another one."""
    arun(interrupt(make_cfg(tmp_path)))
    update_preset(monkeypatch, zero_bin=12.55)
    status, refused = arun(restart(make_cfg(tmp_path)))
    assert refused == f"cannot resume scan 'mix': {PLANNED}zero_bin 12.4 -> 12.55; {FINISH}"
    assert "preset_note" not in status


def test_no_helper_names_the_keys_alone():
    """`sensor_changes` returned the differing keys without the preset's differences: a caller taking an empty list
    for "the same sensor" would resume a scan with another model. `sensor_differences` says both."""
    assert not hasattr(scan_job, "sensor_changes")
