"""The daemon's control socket: mode 0600, only its owner can connect (another user is refused by the kernel), and
no scan name can put a capture outside the captures root."""

from __future__ import annotations

import json
import os
import pwd
import socket
import stat
import traceback

import pytest

from e2e_helpers import spadscan
from spadscan.daemon.client import ControlError, call


def as_user(name: str, fn) -> str:
    """Run fn() -> str in a forked child that has dropped root for user `name`; returns what fn returned (or the
    child's traceback, prefixed 'CRASH')."""
    user = pwd.getpwnam(name)
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: only system calls and a little Python, then _exit
        code = 0
        try:
            os.close(r)
            os.setgroups([])
            os.setgid(user.pw_gid)
            os.setuid(user.pw_uid)
            out = fn()
        except BaseException:
            out, code = "CRASH " + traceback.format_exc(), 1
        os.write(w, out.encode())
        os._exit(code)
    os.close(w)
    chunks = []
    while data := os.read(r, 65536):
        chunks.append(data)
    os.close(r)
    os.waitpid(pid, 0)
    return b"".join(chunks).decode()


def try_connect(path: str):
    def connect() -> str:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.connect(path)
            s.sendall(b'{"op": "status"}\n')
            return "connected: " + s.recv(65536).decode()[:40]
        except OSError as exc:
            return f"refused: {os.strerror(exc.errno)}"
        finally:
            s.close()

    return connect


def try_ctl(path: str):
    def ctl() -> str:
        try:
            call(path, "status", timeout_s=5)
            return "answered"
        except ControlError as exc:
            return f"ControlError: {exc}"

    return ctl


def test_only_the_owner_can_connect(make_daemon, sock_dir):
    pytest.importorskip("pwd").getpwnam("nobody")
    if os.getuid() != 0:
        pytest.skip("needs root to act as another user (nobody)")
    daemon = make_daemon().start()
    st = os.stat(daemon.sock)
    assert stat.S_ISSOCK(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o600 and st.st_uid == os.getuid()
    os.chmod(sock_dir, 0o755)  # the folder lets anyone reach the socket: only the socket's mode stands in the way
    path = str(daemon.sock)
    assert as_user("nobody", try_connect(path)) == "refused: Permission denied"
    reply = as_user("nobody", try_ctl(path))
    assert reply.startswith("ControlError: ") and "permission denied" in reply and "\n" not in reply, reply
    # The check can tell: with the socket opened up, the same user gets in.
    os.chmod(path, 0o666)
    try:
        assert as_user("nobody", try_connect(path)).startswith('connected: {"ok": true')
    finally:
        os.chmod(path, 0o600)
    assert as_user("nobody", try_connect(path)) == "refused: Permission denied"
    assert daemon.status()["state"] == "idle"
    assert daemon.stop() == 0, daemon.log()
    assert not daemon.sock.exists(), "the socket file is removed on exit"


ESCAPES = ["../x", "../../etc", "a/b", "a/../../b", "/abs", "/tmp/spadscan-e2e-abs", ".hidden", ".", "..", "",
           "./x", "x/", "~", "~root", "a\x00b", "-rf", "x" * 101, "a\\b", " x", "x\n", "link"]


def tree(path) -> set[str]:
    return {str(p.relative_to(path)) for p in path.rglob("*")}


def test_a_scan_name_cannot_escape_the_captures_root(make_daemon, tmp_path):
    daemon = make_daemon(scan={"views": 4})
    daemon.captures.mkdir()
    outside = tmp_path / "outside"
    outside.mkdir()
    (daemon.captures / "link").symlink_to(outside, target_is_directory=True)  # an existing link leading out
    daemon.start()
    before = tree(tmp_path)
    for name in ESCAPES:
        with pytest.raises(ControlError) as err:
            daemon.call("scan", name=name)
        assert "\n" not in str(err.value)
        assert daemon.status()["state"] == "idle", f"scan name {name!r} started a scan"
    for bad in ([], {"a": 1}, 7, True, None):
        with pytest.raises(ControlError):
            daemon.call("scan", name=bad) if bad is not None else daemon.call("wait")
    for name in ("../x", "/abs", ".hidden"):
        with pytest.raises(ControlError):
            daemon.call("wait", name=name)
    assert tree(tmp_path) == before, "a refused scan name created something"
    assert not os.path.exists("/tmp/spadscan-e2e-abs") and not list(outside.iterdir())

    # The real `ctl` says why in one line.
    r = daemon.ctl("scan", "--name", "../x")
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1 and "scan name" in r.stderr, r.stderr
    # A good name still works, and lands inside the root.
    r = daemon.ctl("scan", "--name", "ok-1.2_b+c", "--wait")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.splitlines()[-1]) == {"name": "ok-1.2_b+c", "state": "complete"}
    assert (daemon.captures / "ok-1.2_b+c" / "scan.json").is_file()
    assert daemon.stop() == 0, daemon.log()


def test_scan_wait_with_json_ends_with_waits_json_line(make_daemon):
    """`ctl scan --wait --json`: its wait printed the plain reply; now the line `ctl wait --json` prints."""
    daemon = make_daemon(scan={"views": 4})
    daemon.start()
    r = daemon.ctl("scan", "--name", "jw", "--wait", "--json")
    assert r.returncode == 0, r.stderr
    started, waited = map(json.loads, r.stdout.splitlines())
    assert started["scan"] == "jw"
    assert waited["wait"]["name"] == "jw" and waited["wait"]["ended"] == "complete", waited
    assert waited["last_scan"]["name"] == "jw", waited
    assert daemon.stop() == 0, daemon.log()


def test_ctl_without_a_daemon_is_one_line(tmp_path, sock_dir):
    r = spadscan("ctl", "--socket", sock_dir / "none.sock", "status")
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1 and "no daemon is listening" in r.stderr
