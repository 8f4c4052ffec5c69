"""A default the user never chose is named as one: a real sensor on an arm nobody chose is refused, a sim sensor
taken by default says so; a captures folder says whether it is missing, or why it cannot be written into or made,
as the real mkdir says it (root included, whom os.access lets through); the daemon's log is in UTC and says so."""

from __future__ import annotations

import errno
import logging
import os
import re
import shutil
import subprocess
import sys
import time

import pytest

from spadscan.commands.daemon import utc_formatter
from spadscan.daemon.config import config_from_dict
from spadscan.protocol.errors import ConfigError

from process_helpers import permissions_apply



def load(tmp_path, **tables):
    # No `socket`: the default, in the test's short private folder (conftest); one under tmp_path is too long where
    # TMPDIR is.
    return config_from_dict({"captures": str(tmp_path / "caps"), **tables}, tmp_path / "rig.toml")


@pytest.fixture
def port(tmp_path):
    # The config only looks at the port when the daemon checks its devices: any path will do here.
    return str(tmp_path / "ttyACM0")


@pytest.mark.parametrize("arm, missing", [(None, "no [arm] table"), ({"speed": 0.05}, "[arm] names no backend")])
def test_a_real_sensor_on_an_arm_nobody_chose_is_refused(tmp_path, port, arm, missing):
    tables = {"sensor": {"backend": "serial", "port": port}}
    if arm is not None:
        tables["arm"] = arm
    with pytest.raises(ConfigError) as err:
        load(tmp_path, **tables)
    assert str(err.value) == (
        f"{tmp_path / 'rig.toml'}: {missing}, so the simulated arm ('sim', the default) would carry the real 'serial' "
        f"sensor and its captures would pair real histograms with made-up poses: set [arm] backend = \"ur\" (with "
        f"its keys), or write [arm] backend = \"sim\" for a bench test without an arm")


def test_a_bench_without_an_arm_is_taken_when_written_out(tmp_path, port):
    cfg = load(tmp_path, arm={"backend": "sim"}, sensor={"backend": "serial", "port": port})
    assert cfg.arm.backend == "sim" and cfg.sensor.backend == "serial"


def test_a_sim_sensor_may_leave_the_arm_to_its_default(tmp_path):
    assert load(tmp_path, sensor={"backend": "sim", "mesh": "builtin:sphere"}).arm.backend == "sim"


@pytest.mark.parametrize("tables", [{}, {"sensor": {"frame_timeout_s": 2.0}}])
def test_a_sim_sensor_taken_by_default_says_it_was_the_default(tmp_path, tables):
    with pytest.raises(ConfigError) as err:
        load(tmp_path, **tables)
    assert str(err.value) == (f"{tmp_path / 'rig.toml'}: [sensor] mesh is required for backend 'sim' (no backend is "
                              f"named, so the default 'sim' was taken; set backend = \"i2c\" or \"serial\" for "
                              f"another)")


def test_a_key_of_a_backend_nobody_named_says_the_default_was_taken(tmp_path, port):
    """`host` beside a forgotten backend = "ur": the error speaks of 'sim', which the user never wrote."""
    with pytest.raises(ConfigError) as err:
        load(tmp_path, arm={"host": "192.168.1.10"}, sensor={"backend": "serial", "port": port})
    assert str(err.value).endswith("(no backend is named, so the default 'sim' was taken; set backend = \"ur\" for "
                                   "another)"), str(err.value)
    assert "host" in str(err.value)


def test_a_sim_sensor_named_by_the_user_gets_the_plain_error(tmp_path):
    with pytest.raises(ConfigError, match=r"\[sensor\] mesh is required for backend 'sim'$"):
        load(tmp_path, sensor={"backend": "sim"})


# ---- the captures folder ---------------------------------------------------------------------------------------------
SIM = {"sensor": {"backend": "sim", "mesh": "builtin:sphere"}}


def test_a_missing_captures_parent_is_called_missing(tmp_path):
    with pytest.raises(ConfigError, match=r"folder .*nope/deeper is missing$"):
        config_from_dict({"captures": str(tmp_path / "nope" / "deeper" / "caps"), **SIM}, tmp_path / "rig.toml")


def refuse_mkdir_in(folder, err: int, monkeypatch) -> None:
    """Have every folder made inside `folder` refused with `err` (EROFS: a read-only mount; EACCES: no write
    permission), whoever the process runs as."""
    real_mkdir = os.mkdir

    def mkdir(path, *args, **kwargs):
        if os.path.dirname(os.path.abspath(path)) == str(folder):
            raise OSError(err, os.strerror(err), str(path))
        return real_mkdir(path, *args, **kwargs)

    monkeypatch.setattr(os, "mkdir", mkdir)


@pytest.mark.parametrize("err, said", [(errno.EROFS, "Read-only file system"), (errno.EACCES, "Permission denied")])
def test_a_captures_folder_that_cannot_be_written_into_says_why(tmp_path, monkeypatch, err, said):
    """A read-only mount, or no write permission, as the real mkdir says it (tried, not read from the mode)."""
    (tmp_path / "caps").mkdir()
    refuse_mkdir_in(tmp_path / "caps", err, monkeypatch)
    with pytest.raises(ConfigError) as refused:
        load(tmp_path, **SIM)
    assert str(refused.value) == f"{tmp_path / 'rig.toml'}: captures {tmp_path / 'caps'}: cannot write into it ({said})"


def test_a_captures_root_that_cannot_be_made_says_so(tmp_path, monkeypatch):
    refuse_mkdir_in(tmp_path, errno.EROFS, monkeypatch)
    with pytest.raises(ConfigError, match=r"captures .*caps: cannot create it \(Read-only file system\)$"):
        load(tmp_path, **SIM)


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs a Linux /proc")
@pytest.mark.parametrize("captures, said", [("/proc", "cannot write into it ("),
                                            ("/proc/spadscan-test", "cannot create it (")])
def test_a_captures_folder_that_os_access_passes_but_no_one_can_write_is_refused(tmp_path, captures, said):
    """/proc: os.access says yes to root (whom the permission bits do not stop), yet the kernel makes no folder in
    it, for root neither; for another user the refusal is the same."""
    with pytest.raises(ConfigError) as refused:
        config_from_dict({"captures": captures, **SIM}, tmp_path / "rig.toml")
    assert str(refused.value).startswith(f"{tmp_path / 'rig.toml'}: captures {captures}: {said}"), str(refused.value)


def test_loading_a_config_makes_nothing_in_or_for_its_captures(tmp_path):
    (tmp_path / "caps").mkdir()
    load(tmp_path, **SIM)
    assert list((tmp_path / "caps").iterdir()) == []
    config_from_dict({"captures": str(tmp_path / "new"), **SIM}, tmp_path / "rig.toml")
    assert not (tmp_path / "new").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["caps"]


def test_a_captures_folder_this_user_may_not_write_says_so(tmp_path, sock_dir):
    """The real file mode, checked by `spadscan daemon --check` in a process it binds (root too)."""
    (tmp_path / "caps").mkdir(mode=0o500)
    config = tmp_path / "rig.toml"
    config.write_text(f'captures = "{tmp_path / "caps"}"\nsocket = "{sock_dir / "s.sock"}"\n'
                      '[sensor]\nbackend = "sim"\nmesh = "builtin:sphere"\n')
    r = subprocess.run(permissions_apply() + [sys.executable, "-m", "spadscan.cli", "daemon", "--config", str(config),
                                              "--check"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and r.stdout == "" and r.stderr.count("\n") == 1, r.stderr
    assert re.fullmatch(r"spadscan: error: .*rig\.toml: captures .*caps: cannot write into it \(Permission denied\)\n",
                        r.stderr), r.stderr


@pytest.mark.parametrize("folder, said", [("locked", "cannot write into it (Permission denied)"),
                                          ("file", "a file, not a folder"), ("missing", "no such folder")])
def test_a_socket_folder_the_daemon_cannot_use_is_refused_by_the_check(tmp_path, folder, said):
    """`daemon --check` passed a socket folder this user may not write into, and the start failed after the devices
    had connected; a file where the folder should be was called "no such folder"."""
    (tmp_path / "locked").mkdir(mode=0o500)
    (tmp_path / "file").write_text("")
    config = tmp_path / "rig.toml"
    config.write_text(f'captures = "{tmp_path / "caps"}"\nsocket = "{tmp_path / folder / "s.sock"}"\n'
                      '[sensor]\nbackend = "sim"\nmesh = "builtin:sphere"\n')
    r = subprocess.run(permissions_apply() + [sys.executable, "-m", "spadscan.cli", "daemon", "--config", str(config),
                                              "--check"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and r.stdout == "", r.stderr
    assert r.stderr == f"spadscan: error: {config}: socket folder {tmp_path / folder}: {said}\n"


def test_a_captures_folder_on_a_real_read_only_mount_is_refused(tmp_path, sock_dir):
    """A read-only bind mount of the folder, in a mount namespace of the checking process's own (so nothing outside
    it sees the mount); skipped where the process may not make one."""
    caps = tmp_path / "caps"
    caps.mkdir()
    config = tmp_path / "rig.toml"
    config.write_text(f'captures = "{caps}"\nsocket = "{sock_dir / "s.sock"}"\n'
                      '[sensor]\nbackend = "sim"\nmesh = "builtin:sphere"\n')
    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("no unshare: no mount namespace for a read-only mount")
    mount = f'mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" "$1" || exit 99; shift; exec "$@"'
    r = subprocess.run([unshare, "--mount", "sh", "-c", mount, "sh", str(caps), sys.executable, "-m", "spadscan.cli",
                        "daemon", "--config", str(config), "--check"], capture_output=True, text=True, timeout=120)
    if r.returncode == 99 or "unshare:" in r.stderr:
        pytest.skip(f"no read-only bind mount here: {r.stderr.strip()}")
    assert r.returncode == 1 and r.stdout == "" and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr == f"spadscan: error: {config}: captures {caps}: cannot write into it (Read-only file system)\n"


# ---- the log's clock -------------------------------------------------------------------------------------------------
STAMP = 1_796_461_349.212
"""2026-12-05 09:02:29.212 UTC (04:02:29 in New York)."""


def test_the_log_is_in_utc_and_says_so(monkeypatch):
    monkeypatch.setenv("TZ", "America/New_York")  # the local clock is 5 h behind UTC in December
    time.tzset()
    try:
        record = logging.LogRecord("spadscan.daemon", logging.INFO, __file__, 1, "listening on %s", ("x.sock",), None)
        record.created, record.msecs = STAMP, 212.0
        line = utc_formatter().format(record)
    finally:
        monkeypatch.undo()
        time.tzset()
    assert line == "2026-12-05T09:02:29.212Z spadscan daemon: INFO listening on x.sock"
    assert re.match(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z ", line)
