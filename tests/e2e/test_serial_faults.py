"""The daemon on a serial TMF8820 (`[sensor] backend = "serial"`) whose port is the pty of a simulated Arduino bridge
that this test drives: corrupt and partial lines never reach the capture (stored histograms equal, bit for bit, what
the bridge sent for good frames), and a bridge that goes silent pauses the scan with the reason until it is resumed.
"""

from __future__ import annotations

import json
import re
import threading
import time

import numpy as np
import pytest

from e2e_helpers import assert_every_pose_once, chunk_digests, published_prefix, wait_for
from spadscan.daemon.sensor.sim_bridge import FAULTS, BridgeResult, SimBridge
from spadscan.protocol.capture_reader import CaptureReader

JUNK = (b"5,6,7,8\n", b"#Raw,65,4,1,2,3\n", b"\xff\xfe#Obj,65,1\r\n", b"#Raw,65,0," + b"9," * 200 + b"\n")
"""Partial lines (a mid-line start, a line cut short, line noise, an overlong line) sent between frames."""


class Feeder:
    """Sends frames to the bridge in a thread: frame k carries k in its reference bin 0 and in bin 0 of every zone;
    every third frame has one of the bridge's faults, and partial lines go between frames."""

    def __init__(self, bridge: SimBridge, period_s: float = 0.02, seed: int = 0):
        self.bridge, self.period_s = bridge, period_s
        self.rng = np.random.default_rng(seed)
        self.good: dict[int, np.ndarray] = {}
        self.bad: dict[int, str] = {}
        self.k = 0
        self._stop = threading.Event()
        self._running = threading.Event()
        self._sending = threading.Lock()  # held while one frame (and its junk) is queued
        self._thread = threading.Thread(target=self._run, name="e2e-bridge-feeder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            with self._sending:
                if self._running.is_set():
                    self._send_next()

    def _send_next(self) -> None:
        self.k += 1
        k = self.k
        counts = self.rng.integers(0, 1 << 24, size=(10, 128), dtype=np.int64)  # all three byte planes
        counts[:, 0] = k
        fault = FAULTS[(k // 3) % len(FAULTS)] if k % 3 == 0 else None
        if fault is None:
            self.good[k] = counts
        else:
            self.bad[k] = fault
        self.bridge.send_frame(counts, BridgeResult(result_no=k % 256, systick=k), fault=fault,
                               at=1 + k % 27)
        if k % 5 == 0:
            self.bridge.send(JUNK[(k // 5) % len(JUNK)])

    def start(self) -> None:
        self._running.set()

    def hold(self) -> None:
        """Stop sending (the sensor goes silent) and wait until what was queued is written."""
        with self._sending:  # a frame being queued now is queued whole before this returns
            self._running.clear()
        self.bridge.flush()

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


@pytest.fixture
def bridge(tmp_path):
    (tmp_path / "bridge").mkdir()
    # A short write timeout: a frame written while the daemon is not reading is dropped after this long, as a USB
    # bridge's output is lost when nobody reads it.
    with SimBridge(tmp_path / "bridge", write_timeout_s=1.0) as b:
        feeder = Feeder(b)
        try:
            yield b, feeder
        finally:
            feeder.close()


def serial_daemon(make_daemon, port: str, **sections):
    sensor = {"backend": "serial", "port": port, "mesh": None, "rays_per_zone": None, **sections.pop("sensor", {})}
    return make_daemon(sensor=sensor, **sections)


def held_mid_scan(make_daemon, b: SimBridge, feeder: Feeder, name: str, frame_timeout_s: float):
    """A started daemon whose scan `name` (12 poses of 2 frames) has published 3 poses, its bridge's feeder then held
    (nothing more is sent)."""
    feeder.start()
    daemon = serial_daemon(make_daemon, b.port, sensor={"frame_timeout_s": frame_timeout_s},
                           arm={"motion_time_s": 0.1}, scan={"views": 12, "frames_per_pose": 2, "chunk_size": 2})
    daemon.start()
    daemon.call("scan", name=name)
    daemon.wait_pose(name, 3)
    feeder.hold()
    return daemon


def assert_only_good_frames(data, feeder: Feeder) -> None:
    """Every stored frame is a good frame the bridge sent, bit for bit; none is a corrupt one."""
    assert data.reference is not None
    for hist, ref, meta in zip(data.hists, data.reference, data.meta):
        k = int(ref[0])
        assert k not in feeder.bad, f"frame {k} sent with fault {feeder.bad[k]!r} reached the capture"
        assert k in feeder.good, f"stored frame {k} was never sent"
        sent = feeder.good[k]
        assert hist.dtype == np.uint32 and ref.dtype == np.uint32
        np.testing.assert_array_equal(ref, sent[0])
        np.testing.assert_array_equal(hist, sent[1:])
        assert meta["extra"]["systick"] == k


@pytest.mark.slow
def test_corrupt_serial_frames_never_reach_the_capture(make_daemon, tmp_path, bridge):
    b, feeder = bridge
    feeder.start()
    daemon = serial_daemon(make_daemon, b.port, scan={"views": 8, "frames_per_pose": 3, "chunk_size": 3}).start()
    r = daemon.ctl("scan", "--name", "serial", "--wait", timeout=180)
    assert r.returncode == 0, r.stderr + daemon.log()
    sensor = daemon.status()["sensor"]
    feeder.hold()
    data = assert_every_pose_once(tmp_path / "caps" / "serial", 8, 3)
    assert_only_good_frames(data, feeder)
    # The faults did reach the daemon (the test is not vacuous): corrupt lines skipped, faulty frames dropped.
    assert sensor["corrupt_lines"] > 0 and sensor["frames_dropped"] > 0, sensor
    assert len(feeder.bad) >= len(FAULTS), "every kind of fault was sent at least once"
    assert daemon.stop() == 0, daemon.log()


@pytest.mark.slow
def test_silent_serial_sensor_pauses_and_resume_completes(make_daemon, tmp_path, bridge):
    b, feeder = bridge
    daemon = held_mid_scan(make_daemon, b, feeder, "quiet", frame_timeout_s=1.0)
    # the bridge stopped sending: the sensor is silent, after the error line the UW firmware prints
    b.send(b"#Err,inter,2,but no data\n")
    status = daemon.wait_state("paused", 30)
    assert "sensor silent" in status["reason"], status
    # The reason names the bridge's last word and what to do, not only the timeout.
    assert re.search(r"no complete frame within 1 s \(frame_timeout_s\) at pose \d+; the bridge reported "
                     r"'inter,2,but no data' [\d.]+ s ago and no frame since; .*reset or replug the bridge",
                     status["reason"]), status
    assert status["last_error"] == status["reason"]
    folder = tmp_path / "caps" / "quiet"
    poses, digests = published_prefix(folder)
    assert poses == list(range(status["pose"])) and CaptureReader(folder).state == "running"
    time.sleep(1.5)  # a paused scan stays paused while the sensor is silent
    assert daemon.status()["state"] == "paused" and chunk_digests(folder) == digests

    feeder.start()
    r = daemon.ctl("resume")
    assert r.returncode == 0, r.stderr
    r = daemon.ctl("wait", "quiet", timeout=180)
    assert r.returncode == 0 and json.loads(r.stdout)["state"] == "complete", r.stderr + daemon.log()
    data = assert_every_pose_once(folder, 12, 2)
    assert_only_good_frames(data, feeder)
    after = chunk_digests(folder)
    assert all(after[n] == d for n, d in digests.items()), "a chunk published before the silence changed"
    feeder.hold()
    assert daemon.stop() == 0, daemon.log()


@pytest.mark.slow
def test_a_replugged_bridge_that_sets_its_sensor_up_again_is_waited_for_not_paused(make_daemon, tmp_path, bridge):
    """A replug that powered the sensor off: the UW firmware downloads the sensor's firmware again, prints "FW
    downloaded" and takes seconds (a 4 s wait for the short-range command, a calibration) before its first record.
    The scan waits for that start, longer than frame_timeout_s, and completes without a pause."""
    b, feeder = bridge
    daemon = held_mid_scan(make_daemon, b, feeder, "replug", frame_timeout_s=4.0)
    b.unplug()
    b.replug()
    # The firmware prints nothing before the port is open again (a real bridge's download takes a while too).
    wait_for(lambda: daemon.status()["sensor"].get("reconnects", 0) >= 1, "the daemon to reopen the port")
    b.boot(0x6E, start_s=6.0)  # its first record 1.5x frame_timeout_s after "FW downloaded"
    feeder.start()
    ended = wait_for(lambda: (s := daemon.status())["state"] != "scanning" and s, "the scan to end or pause", 180)
    assert ended["state"] == "idle" and ended["last_scan"] == {"name": "replug", "state": "complete"}, (
        ended, daemon.log())
    assert ended["sensor"]["downloads"] == 1 and not ended.get("last_error"), ended
    assert "the sensor is starting again (its bridge set it up afresh)" in daemon.log()
    data = assert_every_pose_once(tmp_path / "caps" / "replug", 12, 2)
    assert_only_good_frames(data, feeder)
    feeder.hold()
    assert daemon.stop() == 0, daemon.log()
