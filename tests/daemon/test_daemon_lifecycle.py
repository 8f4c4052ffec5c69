"""`spadscan daemon` as a real process: one daemon per captures root (whatever its socket), a clean shutdown on
SIGHUP, and `--check` refusing what start-up refuses while another daemon runs, but for a daemon already serving the
config's socket (its own, running): the config is valid all the same."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest

from spadscan.daemon.client import call
from spadscan.protocol.capture_reader import CaptureReader

from test_daemon_process import RIG, Daemons, spadscan, wait_for


@pytest.fixture
def daemons(tmp_path):
    d = Daemons(tmp_path)
    yield d
    d.stop_all()


def rig_on(tmp_path: Path, sock_dir: Path, name: str, views: int = 24) -> tuple[Path, Path]:
    """A rig config `name`.toml on the shared captures root tmp_path/caps, with a socket of its own in sock_dir."""
    sock = sock_dir / f"{name}.sock"
    rig = tmp_path / f"{name}.toml"
    rig.write_text(RIG.format(socket=sock, auto="true").replace("views = 24", f"views = {views}"))
    return rig, sock


def one_line_error(r) -> str:
    assert r.returncode == 1, (r.returncode, r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("spadscan: error: ") and "Traceback" not in r.stderr, r.stderr
    return lines[0]


def test_a_second_daemon_on_the_same_captures_root_is_refused(tmp_path, sock_dir, daemons):
    rig_a, sock_a = rig_on(tmp_path, sock_dir, "a", views=400)
    rig_b, sock_b = rig_on(tmp_path, sock_dir, "b")
    a = daemons.start(rig_a, sock_a)
    call(sock_a, "scan", name="shared")
    wait_for(lambda: call(sock_a, "status")["pose"] >= 2, "a few poses")

    for args in (("daemon", "--config", rig_b, "--check"), ("daemon", "--config", rig_b)):
        line = one_line_error(spadscan(*args))
        assert line.startswith(f"spadscan: error: {rig_b}: captures root {tmp_path / 'caps'} is in use by another "
                               f"daemon (pid {a.pid})"), line  # named with its config file, as every start-up error
    assert not sock_b.exists()
    assert call(sock_a, "status")["state"] == "scanning"  # A's scan goes on, untouched

    # A dies without cleaning up: the kernel drops its lock, and B takes the root (and the interrupted scan) over.
    os.kill(a.pid, signal.SIGKILL)
    a.wait(timeout=30)
    daemons.start(rig_b, sock_b)
    status = call(sock_b, "status")
    assert status["scan"] == "shared", status
    assert spadscan("ctl", "--socket", sock_b, "abort").returncode == 0


def test_sighup_shuts_the_daemon_down_cleanly(tmp_path, sock_dir, daemons):
    rig, sock = rig_on(tmp_path, sock_dir, "hup", views=400)
    proc = daemons.start(rig, sock)
    call(sock, "scan", name="hup")
    wait_for(lambda: call(sock, "status")["pose"] >= 2, "a few poses")
    proc.send_signal(signal.SIGHUP)
    assert proc.wait(timeout=30) == 0, daemons.log(proc)
    log = daemons.log(proc)
    assert "SIGHUP received" in log and "shutting down" in log, log
    assert not sock.exists()
    capture = CaptureReader(tmp_path / "caps" / "hup")
    assert capture.state == "running"  # left resumable, and its reason recorded
    assert "daemon stopped" in json.dumps(capture.manifest)


def test_check_on_the_config_of_a_running_daemon_says_it_is_valid_and_the_daemon_runs(tmp_path, sock_dir, daemons):
    """The config's own daemon holds its socket and its captures root: the config is valid all the same, and `--check`
    says so in one line, with that daemon, and exit status 0 (it used to fail on the socket alone)."""
    rig, sock = rig_on(tmp_path, sock_dir, "a")
    a = daemons.start(rig, sock)
    r = spadscan("daemon", "--config", rig, "--check")
    assert r.returncode == 0 and r.stderr == "", (r.returncode, r.stdout, r.stderr)
    assert r.stdout.startswith(f"{rig}: the config is valid (sim arm, sim sensor, default scan of 24 poses, "), r.stdout
    assert r.stdout.endswith(f"; a daemon is already running on {sock} (pid {a.pid})\n"), r.stdout
    assert len(r.stdout.splitlines()) == 1, r.stdout

    # Another rig on the same socket, with a captures root of its own: valid too, the daemon's root named.
    other = tmp_path / "other.toml"
    other.write_text(rig.read_text().replace('captures = "caps"', 'captures = "caps-other"'))
    r = spadscan("daemon", "--config", other, "--check")
    assert r.returncode == 0 and r.stdout.endswith(f"; a daemon is already running on {sock} (pid {a.pid}, captures "
                                                   f"root {tmp_path / 'caps'})\n"), (r.stdout, r.stderr)
    assert call(sock, "status")["daemon"]["pid"] == a.pid  # asked, and left running


def test_a_captures_root_moved_away_is_locked_again_by_the_next_scan(tmp_path, sock_dir, daemons):
    """The operator moves the captures folder away while the daemon runs: its next scan makes the folder again and
    takes its lock first, so that a second daemon started on it is refused, not let in to take that scan over."""
    rig_a, sock_a = rig_on(tmp_path, sock_dir, "a", views=4)
    rig_b, _ = rig_on(tmp_path, sock_dir, "b")
    a = daemons.start(rig_a, sock_a)
    call(sock_a, "scan", name="old")
    wait_for(lambda: (call(sock_a, "status").get("last_scan") or {}).get("state") == "complete", "scan 'old' done")
    (tmp_path / "caps").rename(tmp_path / "caps-archive")
    call(sock_a, "scan", name="m1", options={"views": 400})
    line = one_line_error(spadscan("daemon", "--config", rig_b))
    assert f"is in use by another daemon (pid {a.pid})" in line, line
    assert "locked again" in daemons.log(a)
    assert (tmp_path / "caps-archive" / "old").is_dir() and call(sock_a, "status")["scan"] == "m1"
