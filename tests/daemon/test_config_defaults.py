"""A default the user never chose is named as one: a real sensor on an arm nobody chose is refused, a sim sensor
taken by default says so; a captures folder says whether it is missing, read-only or not writable; the daemon's log
is in UTC and says so."""

from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
import time

import pytest

from spadscan.commands.daemon import utc_formatter
from spadscan.daemon import config as config_module
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


def test_a_captures_folder_on_a_read_only_mount_says_so(tmp_path, monkeypatch):
    (tmp_path / "caps").mkdir()
    real_statvfs = os.statvfs

    class ReadOnly:
        def __init__(self, path):
            self.f_flag = real_statvfs(path).f_flag | os.ST_RDONLY

    # A read-only mount as the kernel shows it: no write access for anyone, ST_RDONLY in its flags.
    monkeypatch.setattr(config_module.os, "access", lambda path, mode: not mode & os.W_OK)
    monkeypatch.setattr(config_module.os, "statvfs", ReadOnly)
    with pytest.raises(ConfigError, match=r"captures .*caps: folder .*caps is on a read-only file system$"):
        load(tmp_path, **SIM)


def test_a_captures_folder_this_user_may_not_write_says_so(tmp_path, sock_dir):
    """The real file mode, checked by `spadscan daemon --check` in a process it binds (root too)."""
    (tmp_path / "caps").mkdir(mode=0o500)
    config = tmp_path / "rig.toml"
    config.write_text(f'captures = "{tmp_path / "caps"}"\nsocket = "{sock_dir / "s.sock"}"\n'
                      '[sensor]\nbackend = "sim"\nmesh = "builtin:sphere"\n')
    r = subprocess.run(permissions_apply() + [sys.executable, "-m", "spadscan.cli", "daemon", "--config", str(config),
                                              "--check"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and r.stdout == "" and r.stderr.count("\n") == 1, r.stderr
    assert re.fullmatch(r"spadscan: error: .*rig\.toml: captures .*caps: folder .*caps is not writable by this user\n",
                        r.stderr), r.stderr


def test_a_captures_folder_without_write_permission_is_not_called_read_only(tmp_path, monkeypatch):
    (tmp_path / "caps").mkdir()
    monkeypatch.setattr(config_module.os, "access", lambda path, mode: not mode & os.W_OK)
    with pytest.raises(ConfigError, match=r"folder .*caps is not writable by this user$"):
        load(tmp_path, **SIM)


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
