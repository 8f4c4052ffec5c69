"""A daemon refused because another one listens on its socket says how to stop that one, and the command it gives
works as written: `spadscan ctl` looks in its default socket only, so any other path goes with --socket."""

from __future__ import annotations

import shlex

import pytest

from spadscan.daemon import client
from spadscan.daemon.client import call
from spadscan.daemon.control import ControlServer, check_socket_path
from spadscan.protocol.errors import ConfigError

from test_daemon_lifecycle import one_line_error, rig_on
from test_daemon_process import Daemons, spadscan, wait_for


@pytest.fixture
def daemons(tmp_path):
    started = Daemons(tmp_path)
    yield started
    started.stop_all()


async def echo(request: dict) -> dict:
    return {"echo": request.get("op")}


def refusal(arun, path) -> str:
    """The refusal `check_socket_path` gives while a server listens on `path`."""

    async def scenario():
        async with ControlServer(path, echo):
            with pytest.raises(ConfigError) as info:
                check_socket_path(path)
            return str(info.value)

    return arun(scenario())


def test_a_socket_of_the_config_is_named_in_the_command(arun, sock_dir):
    path = sock_dir / "rig.sock"
    said = refusal(arun, path)
    assert said == (f"another daemon is already listening on {path} "
                    f"(stop it with `spadscan ctl --socket {path} shutdown`)")


def test_the_default_socket_needs_no_option(arun):
    path = client.default_socket_path()  # (in the test's private folder: conftest)
    assert refusal(arun, path).endswith("(stop it with `spadscan ctl shutdown`)")


def test_spadscan_socket_in_the_environment_is_the_default(arun, sock_dir, monkeypatch):
    """`spadscan ctl` reads $SPADSCAN_SOCKET as the daemon does: with it set to the path, no option is needed."""
    path = sock_dir / "env.sock"
    monkeypatch.setenv("SPADSCAN_SOCKET", str(path))
    assert refusal(arun, path).endswith("(stop it with `spadscan ctl shutdown`)")


def test_a_path_a_shell_would_split_is_quoted(arun, sock_dir):
    folder = sock_dir / "my rig"
    folder.mkdir()
    said = refusal(arun, folder / "s.sock")
    command = said.split("`")[1]
    assert shlex.split(command) == ["spadscan", "ctl", "--socket", str(folder / "s.sock"), "shutdown"], said


def test_the_command_a_second_daemon_gives_stops_the_first(tmp_path, sock_dir, daemons, monkeypatch):
    """As an operator does it: a second daemon on the same config is refused; the command it names stops the
    first. (`spadscan ctl`'s default socket, for the commands started here, is one nobody listens on: a command
    without --socket must not reach a daemon of the machine's.)"""
    monkeypatch.setenv("SPADSCAN_SOCKET", str(sock_dir / "default.sock"))
    rig, sock = rig_on(tmp_path, sock_dir, "custom")
    first = daemons.start(rig, sock)
    line = one_line_error(spadscan("daemon", "--config", rig))
    assert f"another daemon is already listening on {sock}" in line, line
    program, *args = shlex.split(line.split("`")[1])
    assert program == "spadscan", line
    r = spadscan(*args)
    assert r.returncode == 0, (line, r.stdout, r.stderr)
    assert first.wait(timeout=60) == 0
    wait_for(lambda: not sock.exists(), "the first daemon's socket to go")
    with pytest.raises(client.ControlError):
        call(sock, "status")
