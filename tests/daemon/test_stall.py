"""A daemon that was itself not running (SIGSTOP/SIGCONT, a suspended laptop) does not blame the sensor: the frame
wait it slept through is begun again, and status counts the stall."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from spadscan.daemon.client import call
from spadscan.daemon.stall import StallWatch

from test_daemon_process import daemons, spadscan, wait_for  # noqa: F401 (daemons: a fixture)

RIG = """
captures = "caps"
socket = "{socket}"
[arm]
backend = "sim"
motion_time_s = 0.0
hand_eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.05], [0, 0, 0, 1]]
[sensor]
backend = "sim"
mesh = "builtin:sphere"
rays_per_zone = 16
frame_time_s = 0.25
frame_timeout_s = 1.5
[scan]
views = 12
frames_per_pose = 2
settle_s = 0.0
radius_m = 0.4
target = [0, 0, 0.1]
"""


def test_a_stopped_daemon_waits_again_for_the_frame_instead_of_pausing_on_the_sensor(tmp_path, sock_dir, daemons):
    """SIGSTOP the daemon mid-scan for longer than frame_timeout_s, then SIGCONT: the scan goes on to the end, never
    paused with "sensor silent", and status says the daemon stalled."""
    sock = sock_dir / "ctl.sock"
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG.format(socket=sock))
    proc = daemons.start(rig, sock)
    assert spadscan("ctl", "--socket", sock, "scan", "--name", "held").returncode == 0
    wait_for(lambda: call(sock, "status")["pose"] >= 2, "two poses")
    os.kill(proc.pid, signal.SIGSTOP)
    try:
        time.sleep(4.0)  # the daemon stands still for longer than its frame timeout (1.5 s); nothing is asserted here
    finally:
        os.kill(proc.pid, signal.SIGCONT)
    status = wait_for(lambda: (s := call(sock, "status"))["state"] in ("idle", "paused") and s, "the scan to end",
                      timeout_s=120)
    assert status["state"] == "idle", status["reason"]  # today's code paused here: "sensor silent: ..."
    assert status["last_scan"] == {"name": "held", "state": "complete"}, (status, daemons.log(proc))
    assert status["daemon_stalls"]["count"] >= 1 and status["daemon_stalls"]["total_s"] >= 3.0, status
    assert "sensor silent" not in daemons.log(proc)


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_the_watch_counts_a_gap_between_ticks_and_one_still_open():
    clock = Clock()
    watch = StallWatch(tick_s=0.1, threshold_s=0.5, clock=clock)
    for _ in range(5):
        clock.t += 0.1
        watch.tick()
    clock.t += 0.45  # a late tick on a busy machine: no stall
    watch.tick()
    assert watch.count == 0 and watch.stalled_between(0, clock.t) == 0
    start = clock.t
    clock.t += 10.0  # stopped: the next tick comes 10 s late
    # Asked before the watch's own tick runs (the timeout that asks may run first): the open gap counts.
    assert abs(watch.stalled_between(start, clock.t) - 9.9) < 1e-9
    assert watch.last_stall() == (start + 0.1, clock.t)
    watch.tick()
    assert watch.count == 1 and abs(watch.total_s - 9.9) < 1e-9
    assert abs(watch.stalled_between(start + 5.0, clock.t) - 5.0) < 1e-9  # only the part inside the window
    assert watch.stalled_between(clock.t, clock.t + 1) == 0
    assert watch.counters() == {"count": 1, "total_s": 9.9}
