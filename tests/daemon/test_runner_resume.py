"""A restarted daemon resumes an interrupted scan only on the rig it was planned with: a changed hand-eye or a
changed sensor (its model, backend or simulated scene) blocks the scan with the keys that differ, so that one
capture never mixes two sensors."""

from __future__ import annotations

import contextlib
import threading

import pytest

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.rig import build_devices, rig_record
from spadscan.daemon.config import config_from_dict
from spadscan.daemon import runner as runner_module
from spadscan.daemon.root_lock import RootLock
from spadscan.daemon.runner import ScanRunner
from spadscan.daemon.scan_job import takeover_note
from spadscan.protocol import sensor_presets
from spadscan.protocol.capture_format import MANIFEST, read_json, write_json_atomic
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import mark_paused
from spadscan.protocol.errors import ConfigError

from test_runner import until

SENSOR = {"backend": "sim", "mesh": "builtin:sphere", "rays_per_zone": 4}


def make_cfg(tmp_path, hand_eye_z: float = 0.05, auto_resume: bool = False, arm: dict | None = None, **sensor):
    hand_eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, hand_eye_z], [0, 0, 0, 1]]
    return config_from_dict({
        # No `socket`: the default, in the test's short private folder (conftest); one under tmp_path is too long
        # where TMPDIR is.
        "captures": str(tmp_path / "caps"), "auto_resume": auto_resume,
        "arm": {"backend": "sim", "motion_time_s": 0.0, "hand_eye": hand_eye, **(arm or {})},
        "sensor": {**SENSOR, **sensor},
        "scan": {"views": 40, "settle_s": 0.0, "radius_m": 0.4, "target": [0, 0, 0.1]}}, tmp_path / "rig.toml")


@contextlib.asynccontextmanager
async def a_daemon(cfg, root_lock: RootLock | None = None):
    """(runner, sensor) of a daemon on cfg, its devices open; the runner shuts down (as on SIGTERM) when the block
    ends."""
    arm, sensor = build_devices(cfg)
    async with DeviceSession([arm, sensor]):
        rig, scene = rig_record(cfg)
        runner = ScanRunner(arm, sensor, cfg, rig=rig, scene=scene, root_lock=root_lock)
        try:
            yield runner, sensor
        finally:
            await runner.shutdown()


async def interrupt(cfg, pause: str | None = None) -> None:
    """A daemon on cfg starts scan 'mix' and stops (as on SIGTERM) with a few poses published; `pause`: 'paused'
    once `ctl pause` has paused it, 'pausing' right after `ctl pause` (before the pose in flight is published)."""
    async with a_daemon(cfg) as (runner, _):
        await runner.start("mix")
        await until(lambda: runner.job.next_pose >= 3, "three poses")
        if pause is not None:
            await runner.pause()
            await until(lambda: runner.state == pause, pause)


async def restart(cfg) -> tuple[dict, str | None]:
    """A daemon on cfg takes the scan over; returns its status and why `resume` was refused (None: it resumed)."""
    async with a_daemon(cfg) as (runner, _):
        await runner.recover()
        status = runner.status()
        try:
            await runner.resume()
        except ConfigError as exc:
            return status, str(exc)
        await runner.abort()
        return status, None


@pytest.mark.parametrize("change, keys", [
    ({"power": 5.0}, "(power)"),
    ({"preset": "lcspc-sim"}, "(preset)"),
    ({"ambient": 0.01, "cycles": 1000}, "(ambient, cycles)"),
    ({"mesh": "builtin:cup", "albedo": 0.5}, "(albedo, mesh)"),
])
def test_a_changed_sensor_blocks_the_resume(arun, tmp_path, change, keys):
    arun(interrupt(make_cfg(tmp_path)))
    status, refused = arun(restart(make_cfg(tmp_path, **change)))
    said = f"the rig's [sensor] differs from the one scan 'mix' was planned with {keys}"
    assert status["state"] == "paused" and said in status["reason"], status
    assert refused is not None and said in refused and "abort the scan (`spadscan ctl abort mix`)" in refused
    assert "preset differs" not in refused  # the rig's config changed, not the installed preset
    assert CaptureReader(tmp_path / "caps" / "mix").state == "running"  # nothing was written meanwhile


def test_the_same_sensor_resumes(arun, tmp_path):
    """Keys that change neither the model nor the scene (the noise seed, the frame timeout) do not block."""
    arun(interrupt(make_cfg(tmp_path)))
    status, refused = arun(restart(make_cfg(tmp_path, seed=7, frame_timeout_s=2.0)))
    assert refused is None and "interrupted at pose" in status["reason"], status


def test_a_preset_whose_notes_alone_were_reworded_resumes(arun, tmp_path, monkeypatch):
    """An update that rewords the preset's `notes` (free text: where its numbers come from) leaves what a histogram
    means as it was: the scan it interrupted resumes."""
    arun(interrupt(make_cfg(tmp_path)))
    reworded = sensor_presets.tmf8820().with_(notes="Numbers from a loose fit; reworded.")
    monkeypatch.setitem(sensor_presets.PRESETS, "tmf8820", lambda: reworded)
    status, refused = arun(restart(make_cfg(tmp_path)))
    assert refused is None and "interrupted at pose" in status["reason"], status


def test_a_block_an_earlier_daemon_recorded_is_checked_afresh(arun, tmp_path):
    """A blocked scan's capture records the block with its pause (the dashboard shows it); the next daemon, on the
    rig the scan was planned with again, takes the scan over as interrupted, not as paused with a stale block."""
    capture = tmp_path / "caps" / "mix"
    arun(interrupt(make_cfg(tmp_path)))
    arun(restart(make_cfg(tmp_path, power=5.0)))
    assert "[sensor] differs" in CaptureReader(capture).manifest["paused"]["reason"]
    status, refused = arun(restart(make_cfg(tmp_path)))
    assert refused is None and status["reason"].startswith("interrupted at pose"), status


def test_an_operators_pause_outlasts_a_block(arun, tmp_path):
    """Blocked after the operator's pause: both are said, and recorded; once the rig is restored, the scan is taken
    over paused by the operator, the block gone."""
    capture = tmp_path / "caps" / "mix"
    arun(interrupt(make_cfg(tmp_path), pause="paused"))
    status, refused = arun(restart(make_cfg(tmp_path, power=5.0)))
    said = "the rig's [sensor] differs from the one scan 'mix' was planned with (power)"
    assert status["reason"].startswith(f"paused by user; {said}") and said in refused, status
    assert CaptureReader(capture).manifest["paused"]["reason"] == status["reason"]
    status, refused = arun(restart(make_cfg(tmp_path, auto_resume=True)))
    assert status["state"] == "paused" and status["reason"] == "paused by user", status
    assert refused is None


def test_hand_eye_and_sensor_changed_together_are_both_named(arun, tmp_path):
    arun(interrupt(make_cfg(tmp_path)))
    status, refused = arun(restart(make_cfg(tmp_path, hand_eye_z=0.04, power=2.0)))
    assert "[arm] hand_eye differs" in refused and "[sensor] differs" in refused and "(power)" in refused


def test_taking_a_scan_over_checks_its_poses_off_the_event_loop(arun, tmp_path, monkeypatch):
    """The workspace check of the poses left ran on the event loop: 4,000 of them blocked it 1.4 s, longer than the
    UR watchdog's period, and the controller stopped its script while the daemon took the scan over."""
    arun(interrupt(make_cfg(tmp_path)))
    threads = []
    check = runner_module.check_left

    def recorded(job, arm):
        threads.append(threading.current_thread() is threading.main_thread())
        return check(job, arm)

    monkeypatch.setattr(runner_module, "check_left", recorded)
    status, refused = arun(restart(make_cfg(tmp_path)))
    assert refused is None and threads == [False], (threads, status)


def test_a_scan_paused_when_the_daemon_stopped_is_taken_over_paused_even_with_auto_resume(arun, tmp_path):
    """An operator's pause (or a fault's) is no interruption: a restarted daemon (`systemctl restart`, a crash)
    does not move the arm again by itself; it waits for `ctl resume`, with the pause's reason."""
    cfg = make_cfg(tmp_path, auto_resume=True)
    arun(interrupt(cfg, pause="paused"))
    manifest = CaptureReader(tmp_path / "caps" / "mix").manifest
    assert manifest["paused"]["reason"] == "paused by user" and manifest["state"] == "running"
    status, refused = arun(restart(cfg))
    assert status["state"] == "paused" and status["reason"] == "paused by user", status
    assert refused is None  # `ctl resume` goes on
    assert "paused" not in CaptureReader(tmp_path / "caps" / "mix").manifest  # going on cleared it


def test_a_scan_interrupted_while_it_scanned_still_resumes_by_itself(arun, tmp_path):
    cfg = make_cfg(tmp_path, auto_resume=True)
    arun(interrupt(cfg))
    assert "paused" not in CaptureReader(tmp_path / "caps" / "mix").manifest
    status, _ = arun(restart(cfg))
    assert status["state"] == "scanning", status


def test_a_scan_resumed_by_itself_does_not_tell_the_operator_to_resume_it(arun, tmp_path, caplog):
    cfg = make_cfg(tmp_path, auto_resume=True)
    arun(interrupt(cfg))
    with caplog.at_level("INFO", logger=runner_module.log.name):
        arun(restart(cfg))
    resumed = [r.getMessage() for r in caplog.records if "resumed at pose" in r.getMessage()]
    assert len(resumed) == 1 and "auto_resume continues it" in resumed[0], resumed
    assert "ctl resume" not in resumed[0], resumed


def test_a_scan_stopped_while_its_pause_is_pending_is_taken_over_paused(arun, tmp_path):
    """`ctl pause` waits for the pose in flight; a daemon stopped before that (state 'pausing') leaves the scan
    paused all the same."""
    cfg = make_cfg(tmp_path, auto_resume=True)
    arun(interrupt(cfg, pause="pausing"))
    assert CaptureReader(tmp_path / "caps" / "mix").manifest["paused"]["reason"] == "paused by user"
    status, _ = arun(restart(cfg))
    assert status["state"] == "paused", status


def test_a_takeover_refused_keeps_the_operators_pause(arun, tmp_path):
    """A daemon that reopens a paused scan and then cannot take it over (here a workspace that refuses the poses
    left) leaves the pause recorded, with the time it began: the next daemon, with auto_resume, takes the scan over
    paused instead of moving the arm by itself. The refusal names the plan's pose, not its place among those left."""
    cfg = make_cfg(tmp_path, auto_resume=True)
    arun(interrupt(cfg, pause="paused"))
    capture = tmp_path / "caps" / "mix"
    record = CaptureReader(capture).manifest["paused"]
    tight = make_cfg(tmp_path, auto_resume=True, arm={"workspace_min": [-1, -1, -1], "workspace_max": [1, 1, 0.3]})
    status, refused = arun(restart(tight))
    assert status["state"] == "idle" and "cannot take over" in status["last_error"], status
    first = int(status["last_error"].split(": pose ")[1].split(" of ")[0])
    total = int(status["last_error"].split(": pose ")[1].split(" of ")[1].split(":")[0])
    assert total == 40 and first >= 3, status["last_error"]  # the plan's numbering: 3+ poses were published
    assert CaptureReader(capture).manifest["paused"] == record
    status, refused = arun(restart(cfg))
    assert status["state"] == "paused" and status["reason"] == "paused by user", status
    assert refused is None and "paused" not in CaptureReader(capture).manifest  # `ctl resume` went on


def test_a_pause_keeps_the_time_it_began_across_restarts(arun, tmp_path):
    cfg = make_cfg(tmp_path)
    arun(interrupt(cfg, pause="paused"))
    capture = tmp_path / "caps" / "mix"
    since = CaptureReader(capture).manifest["paused"]["since_utc"]

    async def restart_and_stop():
        async with a_daemon(cfg) as (runner, _):
            await runner.recover()
            await until(lambda: runner.state == "paused", "paused")

    arun(restart_and_stop())
    assert CaptureReader(capture).manifest["paused"]["since_utc"] == since


async def taken_over_and_left(cfg, root) -> tuple[dict, dict]:
    """A daemon on cfg takes the scan over and stops once its capture records the pause it waits in; (its status,
    the record it leaves for the next daemon)."""
    status = await taken_over_and_held(cfg, root)
    return status, CaptureReader(root / "mix").manifest["paused"]


def test_a_takeovers_own_note_is_no_pause_for_the_next_daemon(arun, tmp_path):
    """A daemon without auto_resume takes the interrupted scan over paused and records why it waits (the dashboard
    says it); that note is not the operator's pause: the next daemon with auto_resume goes on by itself (before, it
    stayed paused), and one without says the same as the first."""
    root = tmp_path / "caps"
    arun(interrupt(make_cfg(tmp_path)))
    first, recorded = arun(taken_over_and_left(make_cfg(tmp_path), root))
    assert first["state"] == "paused" and recorded["reason"] == first["reason"], (first, recorded)
    assert recorded["kind"] == "interrupted", recorded
    assert first["reason"].startswith("interrupted at pose") and first["reason"].endswith(
        "(daemon restarted); `spadscan ctl resume` continues"), first
    again, _ = arun(taken_over_and_left(make_cfg(tmp_path), root))
    assert again["reason"] == first["reason"], again
    status, _ = arun(restart(make_cfg(tmp_path, auto_resume=True)))
    assert status["state"] == "scanning", status


NOTE = "interrupted at pose 3/40 (daemon restarted); `spadscan ctl resume` continues"
"""A takeover's note as a daemon words it now, and as daemons before `paused.kind` did."""


def test_a_pause_whose_reason_reads_like_a_takeovers_note_stays_a_pause(arun, tmp_path):
    """The kind of the record tells a takeover's note from a pause, not its wording: a pause (an operator's, a
    fault's) that says what a takeover's note says is still taken over paused, even with auto_resume."""
    cfg = make_cfg(tmp_path, auto_resume=True)
    arun(interrupt(cfg, pause="paused"))
    capture = tmp_path / "caps" / "mix"
    mark_paused(capture, NOTE)  # (the kind a caller does not name: a pause)
    status, refused = arun(restart(cfg))
    assert status["state"] == "paused" and status["reason"] == NOTE, status
    assert refused is None


def set_paused(capture, **record) -> None:
    """Rewrite the `paused` record of the capture's scan.json: its keys given, a key given None removed."""
    manifest = read_json(capture / MANIFEST)
    manifest["paused"].update(record)
    manifest["paused"] = {key: value for key, value in manifest["paused"].items() if value is not None}
    write_json_atomic(capture / MANIFEST, manifest)


def test_a_takeovers_note_is_told_by_its_kind_whatever_it_says(arun, tmp_path):
    """A note reworded (by a later version, say) is still a takeover's note: the next daemon with auto_resume goes
    on by itself."""
    root = tmp_path / "caps"
    arun(interrupt(make_cfg(tmp_path)))
    arun(taken_over_and_left(make_cfg(tmp_path), root))
    set_paused(root / "mix", reason="waiting for the operator after a restart")
    assert CaptureReader(root / "mix").manifest["paused"]["kind"] == "interrupted"
    status, _ = arun(restart(make_cfg(tmp_path, auto_resume=True)))
    assert status["state"] == "scanning", status


@pytest.mark.parametrize("reason, note", [(NOTE, True), ("paused by user", False)])
def test_a_record_without_a_kind_is_read_as_the_daemons_before_wrote_it(arun, tmp_path, reason, note):
    """A scan that a daemon before `paused.kind` left waiting (its note, or the operator's pause) is taken over as
    that daemon meant it, after an update: its note goes on by itself with auto_resume, a pause does not."""
    capture = tmp_path / "caps" / "mix"
    arun(interrupt(make_cfg(tmp_path), pause="paused"))
    set_paused(capture, reason=reason, kind=None)
    status, _ = arun(restart(make_cfg(tmp_path, auto_resume=True)))
    assert status["state"] == ("scanning" if note else "paused"), status


@pytest.mark.parametrize("record, note", [
    ({"reason": NOTE, "kind": "interrupted"}, True),
    ({"reason": "the operator's words", "kind": "interrupted"}, True),
    ({"reason": NOTE, "kind": "pause"}, False),
    ({"reason": NOTE, "kind": "a kind not known yet"}, False),  # (a pause: the arm does not move by itself)
    ({"reason": NOTE}, True),  # written before records had a kind: its wording is all there is
    ({"reason": "interrupted at pose 3/40 (daemon restarted), and the captures' disk is still full"}, True),
    ({"reason": "interrupted at pose 3/40 (daemon restarted)"}, True),
    ({"reason": "paused by user; interrupted at pose 3/40 (daemon restarted)"}, False),
    ({"reason": "interrupted at pose 3/40 (daemon restarted)x"}, False),
    ({"reason": "interrupted at pose 3/40"}, False),
    ({}, False),
])
def test_takeover_note(record, note):
    assert takeover_note({"since_utc": "2024-01-01T00:00:00Z", **record}) is note


async def taken_over_and_held(cfg, root, *, refuse: bool = False, pause: bool = False) -> dict:
    """A daemon on cfg takes the scan over, waits until its capture records the wait; `refuse`: `ctl resume` is then
    refused (the sensor's link down); `pause`: then `ctl pause`. Returns its status (the pause's reply, when paused)
    just before it stops."""
    async with a_daemon(cfg) as (runner, sensor):
        await runner.recover()
        await until(lambda: "paused" in CaptureReader(root / "mix").manifest, "the pause")
        if refuse:
            sensor.inject_link_loss(3600.0)
            with pytest.raises(ConfigError, match="is down"):
                await runner.resume()
        return await runner.pause() if pause else runner.status()


def test_a_takeover_whose_resume_was_refused_is_still_no_pause(arun, tmp_path):
    """A takeover's wait, its resume refused (the sensor's link down), is still no one's pause when the daemon
    stops: the capture records it as the takeover's, and the next daemon with auto_resume goes on by itself (it
    checks the link afresh). The refusal's cause in the record was taken for a pause before."""
    cfg = make_cfg(tmp_path)
    arun(interrupt(cfg))
    refused = arun(taken_over_and_held(cfg, tmp_path / "caps", refuse=True))
    assert refused["state"] == "paused" and "is down" in refused["reason"], refused
    record = CaptureReader(tmp_path / "caps" / "mix").manifest["paused"]
    assert record["kind"] == "interrupted", record
    status, _ = arun(restart(make_cfg(tmp_path, auto_resume=True)))
    assert status["state"] == "scanning", status


def test_a_refused_resume_after_a_takeover_leaves_the_takeovers_note(arun, tmp_path):
    """A takeover's resume refused (the sensor's link down) says the takeover's note first, then the cause, and the
    daemon stopped records the note, not the cause: the next daemon, the link up, said the stale cause before."""
    root = tmp_path / "caps"
    arun(interrupt(make_cfg(tmp_path)))
    refused = arun(taken_over_and_held(make_cfg(tmp_path), root, refuse=True))
    assert refused["reason"].startswith(NOTE.replace("3/40", refused["progress"]) + "; the link to"), refused
    record = CaptureReader(root / "mix").manifest["paused"]
    assert record["kind"] == "interrupted" and "is down" not in record["reason"], record
    status, _ = arun(taken_over_and_left(make_cfg(tmp_path), root))
    assert status["state"] == "paused" and status["reason"] == NOTE.replace("3/40", status["progress"]), status
    recorded = CaptureReader(root / "mix").manifest["paused"]  # (as the daemon stopped: what the dashboard says)
    assert recorded == {**record, "reason": status["reason"]}, (recorded, record)  # (the pause's time kept)


def test_a_takeover_says_its_own_note_whatever_an_earlier_one_recorded(arun, tmp_path):
    """A record of kind interrupted holds an earlier daemon's words of its wait (here a refused resume's cause, as
    daemons before recorded it): the next daemon says its own note, as it stands now, not those words."""
    root = tmp_path / "caps"
    arun(interrupt(make_cfg(tmp_path)))
    arun(taken_over_and_left(make_cfg(tmp_path), root))
    set_paused(root / "mix", reason="the link to sensor sim is down (it reconnects by itself); resume once "
                                    "`spadscan ctl status` shows its link up (pose 3/40)")
    status, _ = arun(taken_over_and_left(make_cfg(tmp_path), root))
    recorded = CaptureReader(root / "mix").manifest["paused"]  # (as the daemon stopped: what the dashboard says)
    assert status["reason"] == NOTE.replace("3/40", status["progress"]) == recorded["reason"], (status, recorded)
    assert recorded["kind"] == "interrupted", recorded


@pytest.mark.parametrize("refuse", [False, True])
def test_ctl_pause_on_a_takeovers_wait_is_the_operators_pause(arun, tmp_path, refuse):
    """`ctl pause` on a scan that waits only because a daemon took it over interrupted makes the wait the operator's
    pause, recorded as one: the next daemon, with auto_resume, keeps it paused instead of moving the arm by itself.
    `ctl pause` did nothing there before (the scan was 'paused' already): the record stayed the takeover's note."""
    root = tmp_path / "caps"
    arun(interrupt(make_cfg(tmp_path)))
    reply = arun(taken_over_and_held(make_cfg(tmp_path), root, refuse=refuse, pause=True))
    assert reply["state"] == "paused" and reply["reason"].startswith("paused by user"), reply
    assert ("; the link to sensor sim is down" in reply["reason"]) is refuse, reply  # (what stands in the way stays)
    assert "interrupted at pose" not in f"{reply['reason']} {reply['last_error']}", reply
    record = CaptureReader(root / "mix").manifest["paused"]
    assert record["kind"] == "pause" and record["reason"] == "paused by user", record
    status, refused = arun(restart(make_cfg(tmp_path, auto_resume=True)))
    assert status["state"] == "paused" and status["reason"] == "paused by user", status
    assert refused is None  # `ctl resume` goes on


def test_ctl_pause_on_a_blocked_takeover_is_the_operators_pause(arun, tmp_path):
    """A scan taken over interrupted and blocked (a changed sensor), then paused by the operator: both are said and
    recorded as a pause; once the rig is restored, the next daemon with auto_resume keeps it paused, the block
    gone."""
    root = tmp_path / "caps"
    arun(interrupt(make_cfg(tmp_path)))
    reply = arun(taken_over_and_held(make_cfg(tmp_path, power=5.0), root, pause=True))
    said = "the rig's [sensor] differs from the one scan 'mix' was planned with (power)"
    assert reply["state"] == "paused" and reply["reason"].startswith(f"paused by user; {said}"), reply
    record = CaptureReader(root / "mix").manifest["paused"]
    assert record["kind"] == "pause" and record["reason"] == reply["reason"], record
    status, refused = arun(restart(make_cfg(tmp_path, auto_resume=True)))
    assert status["state"] == "paused" and status["reason"] == "paused by user", status
    assert refused is None


def test_a_scan_after_the_captures_root_was_moved_locks_it_again(arun, tmp_path, caplog, monkeypatch):
    """The operator moves the captures folder away between scans: the next scan makes it again and holds its lock, so
    that a second daemon on the same folder is refused rather than let in to take over the scan being recorded."""
    import spadscan.daemon.root_lock as root_lock

    monkeypatch.setattr(root_lock, "LOCK_TRIES", 2)
    cfg = make_cfg(tmp_path)
    cfg.captures.mkdir()

    async def scans() -> None:
        with RootLock(cfg.captures) as lock:
            async with a_daemon(cfg, lock) as (runner, _):
                await runner.start("old", {"views": 3})
                assert (await runner.wait("old"))["state"] == "complete"
                cfg.captures.rename(tmp_path / "caps-archive")
                await runner.start("new", {"views": 3})
                with pytest.raises(ConfigError, match="in use by another daemon"):
                    RootLock(cfg.captures).acquire()
                assert (await runner.wait("new"))["state"] == "complete"

    arun(scans())
    assert "locked again" in caplog.text
    assert (tmp_path / "caps-archive" / "old").is_dir() and (cfg.captures / "new").is_dir()
