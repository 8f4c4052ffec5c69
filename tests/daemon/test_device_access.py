"""A sensor's device node that this user cannot use is refused by `--check` in one line naming the fix; an open
refused for permission at start (or at a reconnect) names it too; start-up says when it connects and when each device
is up; a second RTDE client on one arm is named as the likely cause of ur_rtde's "registers in use"."""

from __future__ import annotations

import errno
import grp
import logging
import os
import re
import stat
import subprocess
import sys
from pathlib import Path

import pytest
import serial

from spadscan.daemon.arm.rtde_link import plain_rtde_error
from spadscan.daemon.config import config_from_dict
from spadscan.daemon.devices import LinkLost, Sensor
from spadscan.daemon.app import DeviceSession
from spadscan.daemon.rig import build_devices, preflight
from spadscan.daemon.sensor import serial_bridge
from spadscan.daemon.sensor.device_node import access_fix, is_access_refused, node_problem
from spadscan.daemon.sensor.firmware import load_firmware
from spadscan.protocol.errors import ConfigError, DeviceError

from process_helpers import permissions_apply
from test_arm_ur import connected_arm, make_arm, start_controller

IS_ROOT = os.geteuid() == 0


@pytest.fixture
def pty_port():
    """A pseudo-terminal's path (a character device of this user), its ends closed after the test."""
    master, slave = os.openpty()
    try:
        yield os.ttyname(slave)
    finally:
        os.close(slave)
        os.close(master)


def serial_cfg(tmp_path, port: str, arm: dict | None = None):
    # No `socket`: the default, in the test's short private folder (conftest); one under tmp_path is too long where
    # TMPDIR is.
    return config_from_dict({"captures": str(tmp_path / "caps"), "arm": arm or {"backend": "sim"},
                             "sensor": {"backend": "serial", "port": port}}, tmp_path / "rig.toml")


# ---- --check: what the node is, judged without opening it ------------------------------------------------------------
@pytest.mark.parametrize("kind, make", [("a regular file", lambda p: p.write_text("")),
                                        ("a folder", lambda p: p.mkdir())])
def test_a_port_that_is_not_a_character_device_is_refused_by_the_check(tmp_path, kind, make):
    port = tmp_path / "ttyFAKE"
    make(port)
    with pytest.raises(ConfigError) as err:
        preflight(serial_cfg(tmp_path, str(port)))
    assert str(err.value) == (f"{tmp_path / 'rig.toml'}: [sensor] port {port}: {kind}, not a character device as a "
                              f"serial port is; check the path")


@pytest.mark.skipif(not os.path.exists("/sys/dev/char/1:3/subsystem"), reason="the kernel's /sys/dev/char is absent")
def test_a_character_device_of_another_class_is_refused_by_the_check(tmp_path):
    with pytest.raises(ConfigError, match=r"port /dev/null: a character device of class 'mem', not a serial port "
                                          r"\(class 'tty'\); check the path$"):
        preflight(serial_cfg(tmp_path, "/dev/null"))


def test_a_pty_of_this_user_passes_the_check(tmp_path, pty_port):
    preflight(serial_cfg(tmp_path, pty_port))


def test_a_node_this_user_may_not_read_and_write_names_the_group_to_join(pty_port):
    asked = []

    def no_access(path, mode):
        asked.append((path, mode))
        return False

    problem = node_problem(pty_port, "dialout", "tty", access=no_access)
    assert asked == [(pty_port, os.R_OK | os.W_OK)]
    assert problem.startswith("this user may not read and write it (crw")
    assert "add " in problem and "to the 'dialout' group (sudo usermod -aG dialout " in problem
    assert problem.endswith("then log out and in again") and "\n" not in problem
    assert node_problem(pty_port, "dialout", "tty", access=lambda path, mode: True) is None


def check_as_user(config: Path) -> subprocess.CompletedProcess:
    """`spadscan daemon --check` in a process that file modes bind, as they bind an operator (root too)."""
    return subprocess.run(permissions_apply() + [sys.executable, "-m", "spadscan.cli", "daemon", "--config",
                                                 str(config), "--check"], capture_output=True, text=True, timeout=120)


def test_a_pty_whose_mode_shuts_this_user_out_is_refused_by_the_check(tmp_path, sock_dir, pty_port):
    config = tmp_path / "rig.toml"
    config.write_text(f'captures = "{tmp_path / "caps"}"\nsocket = "{sock_dir / "s.sock"}"\n[arm]\nbackend = "sim"\n'
                      f'[sensor]\nbackend = "serial"\nport = "{pty_port}"\n')
    (tmp_path / "caps").mkdir()
    assert check_as_user(config).returncode == 0, "the port as it is passes"
    mode = os.stat(pty_port).st_mode
    os.chmod(pty_port, 0o000)
    try:
        refused = check_as_user(config)
    finally:
        os.chmod(pty_port, stat.S_IMODE(mode))
    assert refused.returncode == 1 and refused.stdout == "" and refused.stderr.count("\n") == 1, refused.stderr
    assert re.fullmatch(r"spadscan: error: .*rig\.toml: \[sensor\] port .*: this user may not read and write it \(.*"
                        r"then log out and in again\n", refused.stderr), refused.stderr


def test_a_node_of_the_wrong_class_is_named_by_the_class_the_kernel_gives(tmp_path, pty_port):
    """An I2C bus path that leads to a serial port: the kernel's class says so (a fake /sys/dev/char here)."""
    rdev = os.stat(pty_port).st_rdev
    entry = tmp_path / "char" / f"{os.major(rdev)}:{os.minor(rdev)}"
    entry.mkdir(parents=True)
    (entry / "subsystem").symlink_to(tmp_path / "class" / "tty")
    assert node_problem(pty_port, "i2c", "i2c-dev", sys_char=tmp_path / "char") == \
        "a character device of class 'tty', not an I2C bus (class 'i2c-dev'); check the path"
    assert node_problem(pty_port, "dialout", "tty", sys_char=tmp_path / "char") is None


def group_to_give() -> int | None:
    """A named group other than root's that this user may give a file, and other than 'dialout' (the group the fix
    names when the node's own may not read and write it): any group for root, one of an ordinary user's own groups
    (the only ones they may give); None when there is none."""
    if IS_ROOT:
        gids = [g.gr_gid for g in grp.getgrall()]
    else:
        gids = [os.getgid(), *os.getgroups()]
    for gid in gids:
        try:
            name = grp.getgrgid(gid).gr_name
        except KeyError:  # a group with no name here (a container's numeric gid)
            continue
        if gid != 0 and name != "dialout":
            return gid
    return None


def test_the_fix_names_the_nodes_own_group_when_that_group_may_read_and_write_it(tmp_path):
    node = tmp_path / "node"
    node.write_text("")
    gid = group_to_give()
    if gid is None:
        pytest.skip("no named group other than root's and dialout that this user may give a file")
    os.chown(node, -1, gid)
    os.chmod(node, 0o660)
    assert f"to the '{grp.getgrgid(gid).gr_name}' group" in access_fix(str(node), "dialout")
    os.chmod(node, 0o600)  # the group may not: the usual group is named
    assert "to the 'dialout' group" in access_fix(str(node), "dialout")


# ---- start-up: a refused open names the fix; each device says when it is up -----------------------------------------
def refuse_open(port, baud, timeout=None):
    # What pyserial raises for a port this user may not open.
    raise serial.SerialException(errno.EACCES, f"could not open port {port}: [Errno 13] Permission denied: '{port}'")


def connect_error(arun, sensor) -> str:
    """The one line of the DeviceError that connecting `sensor` raises (the sensor closed after)."""
    async def main():
        try:
            await sensor.connect()
        finally:
            await sensor.close()

    with pytest.raises(DeviceError) as err:
        arun(main())
    return str(err.value)


def test_a_port_whose_open_is_refused_names_the_group_at_start(tmp_path, pty_port, monkeypatch, arun):
    monkeypatch.setattr(serial_bridge.serial, "Serial", refuse_open)
    _, sensor = build_devices(serial_cfg(tmp_path, pty_port))
    text = connect_error(arun, sensor)
    assert text.startswith(f"sensor serial {pty_port}: cannot open port at 1000000 baud: [Errno 13]")
    assert "Permission denied" in text and "group (sudo usermod -aG" in text and text.endswith("log out and in again")


def test_an_open_that_fails_for_another_reason_gets_no_group_advice(tmp_path, arun):
    _, sensor = build_devices(serial_cfg(tmp_path, str(tmp_path / "ttyGONE")))
    assert "usermod" not in connect_error(arun, sensor)


def test_a_refused_permission_is_found_behind_the_errors_that_reword_it():
    try:
        try:
            raise PermissionError(errno.EACCES, "Permission denied")
        except OSError:
            raise DeviceError("cannot open") from None
    except DeviceError as exc:
        assert is_access_refused(exc)
    assert not is_access_refused(DeviceError("cannot open: no such file"))


class QuietSensor(Sensor):
    name = "sensor quiet"
    model = None

    async def next_frame(self, timeout_s):
        raise AssertionError("not read")


def test_each_device_says_when_it_is_connected(arun, caplog):
    async def main():
        async with DeviceSession([QuietSensor()]):
            pass

    with caplog.at_level(logging.INFO, logger="spadscan.daemon"):
        arun(main())
    assert [r.getMessage() for r in caplog.records] == ["sensor quiet connected"]


def test_the_ur_arm_says_it_is_connecting_and_for_how_long(arun, caplog):
    sim = start_controller(0.1)
    try:
        async def main():
            async with connected_arm(sim.host):
                pass

        with caplog.at_level(logging.INFO, logger="spadscan.daemon"):
            arun(main())
    finally:
        sim.close()
    said = [r.getMessage() for r in caplog.records]
    assert said == [f"connecting to UR arm {sim.host} (up to 35 s)"]  # "connected": the device session's line


# ---- a second RTDE client on the same arm ----------------------------------------------------------------------------
def test_a_second_client_on_one_arm_is_named_as_the_likely_cause(arun):
    """Two URArms (two daemons) on one controller: the second's input registers are taken by the first."""
    sim = start_controller(0.1)
    try:
        async def main():
            async with connected_arm(sim.host):
                second = make_arm(sim.host)
                try:
                    await second.connect()
                finally:
                    await second.close()

        with pytest.raises(LinkLost) as err:
            arun(main())
    finally:
        sim.close()
    text = str(err.value)
    assert text.startswith(f"UR arm {sim.host}: connection to {sim.host} failed: the arm's RTDE input registers are "
                           f"already in use, most likely by another RTDE client: another spadscan daemon on this arm")
    assert "fieldbus adapter" in text and "\n" not in text


def test_ur_rtdes_other_errors_pass_unchanged():
    assert plain_rtde_error("read: End of file") == "read: End of file"
    said = ("One of the RTDE input registers are already in use! Currently you must disable the EtherNet/IP adapter, "
            "PROFINET or any MODBUS unit configured on the robot.")
    assert plain_rtde_error(said).startswith("the arm's RTDE input registers are already in use, most likely by "
                                             "another RTDE client")


# ---- firmware --------------------------------------------------------------------------------------------------------
def test_a_firmware_path_that_is_a_folder_is_called_one(tmp_path):
    folder = tmp_path / "fw"
    folder.mkdir()
    with pytest.raises(ConfigError, match=r"\[sensor\] firmware .*fw is a folder, not a file"):
        config_from_dict({"captures": str(tmp_path / "caps"), "socket": str(tmp_path / "s.sock"),
                          "arm": {"backend": "sim"}, "sensor": {"backend": "i2c", "bus": 7, "firmware": str(folder)}},
                         tmp_path / "rig.toml")
    with pytest.raises(DeviceError, match=r"fw is a folder, not a file"):
        load_firmware(folder)

