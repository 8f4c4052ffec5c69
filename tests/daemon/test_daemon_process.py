"""`spadscan daemon` and `spadscan ctl` as real processes: kill -9 mid-scan, restart, resume, every pose once."""

from __future__ import annotations

import collections
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from spadscan.daemon.client import ControlError, call
from spadscan.protocol.capture_reader import CaptureReader

RIG = """
captures = "caps"
socket = "{socket}"
auto_resume = {auto}
[arm]
backend = "sim"
motion_time_s = 0.03
hand_eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.05], [0, 0, 0, 1]]
[sensor]
backend = "sim"
mesh = "builtin:sphere"
rays_per_zone = 16
[scan]
views = 24
frames_per_pose = 2
settle_s = 0.0
radius_m = 0.4
target = [0, 0, 0.1]
"""


def write_rig(tmp_path: Path, auto: bool, sock_dir: Path | None = None) -> tuple[Path, Path]:
    """(rig config in tmp_path, its socket in sock_dir, else in tmp_path: pass the sock_dir fixture's short folder,
    as a socket's path under a long TMPDIR passes the 107 bytes a Unix socket may have)."""
    sock = (sock_dir or tmp_path) / "ctl.sock"
    rig = tmp_path / f"rig-{'auto' if auto else 'manual'}.toml"
    rig.write_text(RIG.format(socket=sock, auto=str(auto).lower()))
    return rig, sock


def spadscan(*args, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "spadscan.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


class Daemons:
    """Starts daemon processes and makes sure every one of them is gone at the end."""

    def __init__(self, tmp_path: Path):
        self.tmp_path = tmp_path
        self.procs: list[subprocess.Popen] = []

    def start(self, rig: Path, sock: Path) -> subprocess.Popen:
        log = open(self.tmp_path / f"daemon-{len(self.procs)}.log", "w")
        proc = subprocess.Popen([sys.executable, "-m", "spadscan.cli", "daemon", "--config", str(rig)],
                                stdout=log, stderr=subprocess.STDOUT)
        log.close()
        self.procs.append(proc)
        deadline = time.monotonic() + 60
        while True:
            try:
                call(sock, "status", timeout_s=5)
                return proc
            except ControlError:
                if proc.poll() is not None:
                    raise AssertionError(f"daemon exited with {proc.returncode}: {self.log(proc)}")
                if time.monotonic() > deadline:
                    raise AssertionError(f"daemon did not listen within 60 s: {self.log(proc)}")
                time.sleep(0.05)

    def log(self, proc: subprocess.Popen) -> str:
        return (self.tmp_path / f"daemon-{self.procs.index(proc)}.log").read_text()

    def stop_all(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()
            p.wait(timeout=30)


@pytest.fixture
def daemons(tmp_path):
    d = Daemons(tmp_path)
    yield d
    d.stop_all()


def wait_for(pred, what: str, timeout_s: float = 60.0):
    deadline = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def kill_mid_scan(daemons: Daemons, proc: subprocess.Popen, sock: Path, name: str) -> int:
    """Start scan `name` with the real `ctl`, kill -9 the daemon once a few poses are published; returns how many
    poses the daemon had reported published."""
    r = spadscan("ctl", "--socket", sock, "scan", "--name", name, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["scan"] == name
    seen = wait_for(lambda: (s := call(sock, "status"))["scan"] == name and s["pose"] >= 5 and s["pose"], "poses")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    return seen


def check_every_pose_once(folder: Path, n: int, k: int) -> None:
    data = CaptureReader(folder).load()
    counts = collections.Counter(zip(data.pose_indices.tolist(), [m["frame"] for m in data.meta]))
    assert sorted(counts) == [(i, f) for i in range(n) for f in range(k)]
    assert set(counts.values()) == {1}


@pytest.mark.slow
def test_kill_9_restart_resume_every_pose_once(tmp_path, sock_dir, daemons):
    rig, sock = write_rig(tmp_path, auto=False, sock_dir=sock_dir)
    first = daemons.start(rig, sock)
    assert (os.stat(sock).st_mode & 0o777) == 0o600
    seen = kill_mid_scan(daemons, first, sock, "crash")
    folder = tmp_path / "caps" / "crash"
    r = CaptureReader(folder)
    assert r.state == "running"
    published = sorted(set(r.load().pose_indices.tolist()))
    assert published == list(range(len(published))) and len(published) >= seen  # nothing published was lost
    frames_per_pose = collections.Counter(r.load().pose_indices.tolist())
    assert set(frames_per_pose.values()) == {2}  # no half pose was published

    second = daemons.start(rig, sock)  # replaces the stale socket the killed daemon left
    status = call(sock, "status")
    assert status["state"] == "paused" and status["scan"] == "crash", (status, daemons.log(second))
    assert "interrupted" in status["reason"]
    assert status["pose"] == len(published)
    r = spadscan("ctl", "--socket", sock, "resume")
    assert r.returncode == 0, r.stderr
    r = spadscan("ctl", "--socket", sock, "wait", "crash")
    assert r.returncode == 0 and json.loads(r.stdout) == {"name": "crash", "state": "complete"}, r.stderr
    assert CaptureReader(folder).state == "complete"
    check_every_pose_once(folder, 24, 2)

    # `wait` exits non-zero on abort.
    assert spadscan("ctl", "--socket", sock, "scan", "--name", "short", "--views", "200").returncode == 0
    wait_for(lambda: call(sock, "status")["pose"] >= 1, "a pose")
    r = spadscan("ctl", "--socket", sock, "abort", "--reason", "test abort")
    assert r.returncode == 0, r.stderr
    r = spadscan("ctl", "--socket", sock, "wait", "short")
    assert r.returncode == 1 and json.loads(r.stdout)["state"] == "aborted" and "aborted" in r.stderr

    # SIGTERM: a clean exit, the socket file gone.
    second.send_signal(signal.SIGTERM)
    assert second.wait(timeout=30) == 0, daemons.log(second)
    assert not sock.exists()


@pytest.mark.slow
def test_auto_resume_after_kill_9(tmp_path, sock_dir, daemons):
    rig, sock = write_rig(tmp_path, auto=False, sock_dir=sock_dir)
    auto_rig, _ = write_rig(tmp_path, auto=True, sock_dir=sock_dir)
    first = daemons.start(rig, sock)
    kill_mid_scan(daemons, first, sock, "auto")
    second = daemons.start(auto_rig, sock)
    # A second daemon on the same socket is refused with one line and touches nothing.
    r = spadscan("daemon", "--config", auto_rig)
    assert r.returncode == 1 and "another daemon is already listening" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = spadscan("ctl", "--socket", sock, "wait", "auto")
    assert r.returncode == 0, r.stderr + daemons.log(second)
    check_every_pose_once(tmp_path / "caps" / "auto", 24, 2)
    r = spadscan("ctl", "--socket", sock, "shutdown")
    assert r.returncode == 0 and r.stdout == "the daemon is stopping (a scan in flight stays resumable)\n"
    assert second.wait(timeout=30) == 0, daemons.log(second)
    assert not sock.exists()


def test_bad_config_and_no_daemon_are_one_line_errors(tmp_path, sock_dir):
    rig, sock = write_rig(tmp_path, auto=False, sock_dir=sock_dir)
    rig.write_text(rig.read_text().replace("views = 24", "views = 24\nveiws = 3"))
    r = spadscan("daemon", "--config", rig)
    assert r.returncode == 1 and r.stderr.count("\n") == 1
    assert "unknown key 'veiws'" in r.stderr and str(rig) in r.stderr
    assert not sock.exists() and not (tmp_path / "caps").exists()
    r = spadscan("ctl", "--socket", sock, "status")
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "no daemon is listening" in r.stderr
