"""Faults in a running daemon process: a protective stop (the sim arm's `protective_stop_on_move`, and the simulated
UR controller through the real ur_rtde client), a full disk (a small tmpfs as the captures root) and a silent sim
sensor. Each pauses the scan with the reason in `status`, loses nothing that was published, and `ctl resume`
completes the scan with every pose once.
"""

from __future__ import annotations

import errno
import itertools
import json
import os

import pytest

from e2e_helpers import assert_every_pose_once, chunk_digests, one_line_error, published_prefix, tmpfs, wait_for
from spadscan.protocol.capture_reader import CaptureReader


def paused_with(daemon, words: str, folder) -> tuple[dict, dict]:
    """Wait for the pause; check its reason, that the published poses are a readable prefix and the capture stays
    resumable. Returns (status, chunk digests)."""
    status = daemon.wait_state("paused", 60)
    assert words in status["reason"], status
    poses, digests = published_prefix(folder)
    assert poses == list(range(status["pose"])), (poses, status["pose"])
    assert CaptureReader(folder).state == "running"
    return status, digests


def resume_to_the_end(daemon, name: str, digests: dict) -> None:
    r = daemon.ctl("resume")
    assert r.returncode == 0, r.stderr
    r = daemon.ctl("wait", name, timeout=180)
    assert r.returncode == 0 and json.loads(r.stdout)["state"] == "complete", r.stderr + daemon.log()
    after = chunk_digests(daemon.captures / name)
    assert all(after[n] == d for n, d in digests.items()), "a chunk published before the fault changed"


# ---- protective stop -------------------------------------------------------------------------------------------------
def test_protective_stop_of_the_sim_arm_pauses_and_resume_completes(make_daemon, tmp_path):
    daemon = make_daemon(arm={"protective_stop_on_move": [5]}, scan={"views": 10, "frames_per_pose": 2,
                                                                      "chunk_size": 2}).start()
    daemon.call("scan", name="stop")
    status, digests = paused_with(daemon, "protective stop", tmp_path / "caps" / "stop")
    assert status["pose"] == 4, "the four poses before the stopped move are published"
    assert daemon.status()["state"] == "paused", "a paused scan stays paused"
    resume_to_the_end(daemon, "stop", digests)  # the sim arm has no pendant: resuming clears its stop
    assert_every_pose_once(tmp_path / "caps" / "stop", 10, 2)
    assert daemon.stop() == 0, daemon.log()


_hosts = itertools.count(1)


@pytest.fixture
def ur_controller():
    from spadscan.daemon.ursim.remote import SimURProcess
    from spadscan.protocol.errors import DeviceError

    for _ in range(10):
        try:
            sim = SimURProcess(f"127.79.{os.getpid() % 250}.{next(_hosts) % 240 + 1}", time_scale=0.05)
            break
        except DeviceError:  # the address is taken
            continue
    else:
        raise AssertionError("no free loopback address for the simulated UR controller")
    try:
        yield sim
    finally:
        sim.close()


@pytest.mark.slow
def test_protective_stop_on_the_ur_controller_pauses_and_resume_completes(make_daemon, tmp_path, ur_controller):
    arm = {"backend": "ur", "host": ur_controller.host, "motion_time_s": None, "speed": 0.5, "acceleration": 2.0,
           "hand_eye": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.045], [0, 0, 0, 1]],
           "workspace_min": [0.0, -0.5, 0.02], "workspace_max": [0.9, 0.5, 0.7], "min_reach_m": 0.1,
           "max_reach_m": 0.85, "move_timeout_s": 30.0}
    sensor = {"mesh": "builtin:pyramid", "mesh_offset_m": [0.4, 0.0, 0.0], "rays_per_zone": 8}
    scan = {"views": 8, "radius_m": 0.25, "target": [0.4, 0.0, 0.05], "min_elevation_deg": 30.0,
            "max_elevation_deg": 80.0}
    daemon = make_daemon(arm=arm, sensor=sensor, scan=scan).start()
    daemon.call("scan", name="ur")
    daemon.wait_pose("ur", 2)
    # The stop must come mid-scan however late this test gets to it: the scan is paused first (it goes on at once
    # otherwise), the controller stopped, and the scan's next move meets the stop.
    daemon.call("pause")
    daemon.wait_state("paused")
    ur_controller.protective_stop()
    daemon.call("resume")
    _, digests = paused_with(daemon, "protective stop", tmp_path / "caps" / "ur")
    ur_controller.clear_protective_stop()  # what the operator does on the teach pendant
    resume_to_the_end(daemon, "ur", digests)
    assert_every_pose_once(tmp_path / "caps" / "ur", 8, 1, atol=1e-5)
    assert daemon.stop() == 0, daemon.log()


# ---- disk full -------------------------------------------------------------------------------------------------------
@pytest.fixture
def small_disk(tmp_path, procs):
    """A 2 MiB tmpfs mounted at tmp_path/caps (needs root); unmounted after every process of the test stopped."""
    with tmpfs(tmp_path / "caps", "2m") as mounted:
        if not mounted:
            pytest.skip("cannot mount a small tmpfs here (needs root)")
        try:
            yield tmp_path / "caps"
        finally:
            procs.stop_all()


def fill(folder) -> int:
    """Write a file until the filesystem is full; returns its size in bytes."""
    size = 0
    block = b"\0" * 65536
    with open(folder / "filler", "wb", buffering=0) as f:
        try:
            while True:
                size += f.write(block)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC, exc
        try:  # the last partial block
            while f.write(b"\0" * 512):
                size += 512
        except OSError:
            pass
    return size


@pytest.mark.slow
def test_disk_full_pauses_and_resume_completes(make_daemon, small_disk):
    daemon = make_daemon(captures=small_disk, arm={"motion_time_s": 0.05},
                         scan={"views": 24, "frames_per_pose": 2, "chunk_size": 2}).start()
    daemon.call("scan", name="full")
    daemon.wait_pose("full", 4)
    daemon.call("pause")  # the disk fills mid-scan however late this test gets to it
    daemon.wait_state("paused")
    assert fill(small_disk) > 0
    r = daemon.ctl("resume")  # refused at once, before the arm moves: one pose's files do not fit
    assert "disk full" in one_line_error(r) and "make room" in one_line_error(r)
    status, digests = paused_with(daemon, "disk full", small_disk / "full")
    assert status["last_error"] == status["reason"]
    assert daemon.status()["state"] == "paused"
    r = daemon.ctl("resume")  # before room is made: refused at once, naming the cause; nothing published is touched
    line = one_line_error(r)
    assert "cannot resume scan 'full': cannot reopen the capture: disk full" in line and "make room" in line, line
    status = daemon.status()
    assert status["state"] == "paused" and "disk full" in status["reason"], status
    again = chunk_digests(small_disk / "full")
    assert all(again[n] == d for n, d in digests.items()), "a resume on a full disk changed a published chunk"
    (small_disk / "filler").unlink()  # the operator makes room
    resume_to_the_end(daemon, "full", digests)
    assert_every_pose_once(small_disk / "full", 24, 2)
    assert not [p for p in (small_disk / "full").iterdir() if p.name.startswith(".tmp-")], "half-written chunk left"
    assert daemon.stop() == 0, daemon.log()


def test_disk_full_at_scan_start_is_a_clear_refusal_and_the_name_stays_free(make_daemon, small_disk):
    daemon = make_daemon(captures=small_disk, scan={"views": 6}).start()
    assert fill(small_disk) > 0
    r = daemon.ctl("scan", "--name", "late")
    line = one_line_error(r)
    status = daemon.status()
    assert status["state"] == "idle", "the daemon keeps serving"
    assert "No space left" in status["last_error"], status
    assert not (small_disk / "late").exists(), "the half-made scan folder is left behind"
    (small_disk / "filler").unlink()
    r2 = daemon.ctl("scan", "--name", "late", "--wait")
    assert "internal error" not in line and "No space left" in line, line
    assert "Traceback" not in daemon.log()
    assert r2.returncode == 0, r2.stderr
    assert_every_pose_once(small_disk / "late", 6, 1)
    assert daemon.stop() == 0, daemon.log()


# ---- a silent sim sensor ---------------------------------------------------------------------------------------------
def test_silent_sim_sensor_pauses_and_resume_completes(make_daemon, tmp_path):
    daemon = make_daemon(sensor={"frame_timeout_s": 0.5, "silence_on_frames": [7], "silence_s": 2.0},
                         scan={"views": 10, "frames_per_pose": 2, "chunk_size": 2}).start()
    daemon.call("scan", name="quiet")
    _, digests = paused_with(daemon, "sensor silent", tmp_path / "caps" / "quiet")
    while True:  # a busy machine may stall the daemon past the 0.5 s timeout too: each pause is resumed alike
        wait_for(lambda: not daemon.status()["sensor"]["silent"], "the silence to end", 30)
        daemon.call("resume")
        status = wait_for(lambda: (s := daemon.status())["state"] in ("paused", "idle") and s,
                          "the scan to end or pause again", 180)
        if status["state"] == "idle":
            break
        assert "sensor silent" in status["reason"], status
    assert status["last_scan"] == {"name": "quiet", "state": "complete"}, daemon.log()
    after = chunk_digests(tmp_path / "caps" / "quiet")
    assert all(after[n] == d for n, d in digests.items()), "a chunk published before the fault changed"
    assert_every_pose_once(tmp_path / "caps" / "quiet", 10, 2)
    assert daemon.stop() == 0, daemon.log()
