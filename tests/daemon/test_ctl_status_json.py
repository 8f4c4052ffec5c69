"""`spadscan ctl status --json`: accepted like every other operation's --json (the same JSON as without it), and a
daemon that does not answer (no socket, a stale one, a path no socket can have, one this user may not open) is
printed on standard output as {"ok": false, "error": ...} beside the one error line on stderr and exit status 1;
without --json standard output stays empty. Never a traceback."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from spadscan.cli import main

from process_helpers import permissions_apply

STATUS = {"ok": True, "state": "scanning", "scan": "mug", "pose": 3, "poses": 128, "progress": "3/128",
          "last_error": None, "elapsed_s": 12.5, "scan_elapsed_s": 40.25,
          "started_utc": "2026-01-02T03:04:05.678+00:00"}


def test_status_takes_json_and_prints_the_same_json_on_one_line(tmp_path, monkeypatch, capsys):
    """Scripts pass --json to every operation: `status` refused it (argparse, exit 2)."""
    import spadscan.daemon.client as client

    monkeypatch.setattr(client, "call", lambda path, op, timeout, **request: dict(STATUS))
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), "status"]) == 0
    plain = capsys.readouterr()
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), "status", "--json"]) == 0
    with_json = capsys.readouterr()
    assert with_json.err == plain.err == "" and with_json.out.count("\n") == 1, "one line, as every --json"
    assert json.loads(with_json.out) == json.loads(plain.out) == {k: v for k, v in STATUS.items() if k != "ok"}


def stale_socket(folder: Path) -> str:
    """A socket file nobody listens on (a crashed daemon's), in `folder`: the sock_dir fixture's short one, as a
    socket under a long TMPDIR's tmp_path cannot be made."""
    path = str(folder / "stale.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(path)
    sock.close()
    return path


def no_daemon_at(case: str, folder: Path) -> str:
    if case == "missing":
        return str(folder / "none.sock")
    if case == "stale":
        return stale_socket(folder)
    if case == "not a folder":
        (folder / "file").write_text("")
        return str(folder / "file" / "ctl.sock")
    return str(folder / ("x" * 120) / "ctl.sock")  # longer than a Unix socket's path may be


@pytest.mark.parametrize("case, said", [
    ("missing", "no daemon is listening on"), ("stale", "no daemon is listening on"),
    ("not a folder", "Not a directory"), ("too long", "path too long")])
def test_status_with_json_prints_a_daemon_that_does_not_answer_as_json(sock_dir, capsys, case, said):
    path = no_daemon_at(case, sock_dir)
    assert main(["ctl", "--socket", path, "status", "--json"]) == 1
    captured = capsys.readouterr()
    assert captured.err.startswith("spadscan: error: ") and captured.err.count("\n") == 1 and said in captured.err
    assert json.loads(captured.out) == {"ok": False, "error": captured.err[len("spadscan: error: "):-1]}
    assert main(["ctl", "--socket", path, "status"]) == 1
    assert capsys.readouterr() == ("", captured.err), "without --json: the error line alone, as before"


def test_a_socket_this_user_may_not_open_is_one_line_and_json_not_a_traceback(sock_dir):
    path = stale_socket(sock_dir)
    listening = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    os.unlink(path)
    listening.bind(path)
    listening.listen(1)
    os.chmod(path, 0)
    try:
        r = subprocess.run(permissions_apply() + [sys.executable, "-m", "spadscan.cli", "ctl", "--socket", path,
                                                       "status", "--json"], capture_output=True, text=True, timeout=60)
    finally:
        listening.close()
    assert r.returncode == 1 and "Traceback" not in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert "permission denied" in r.stderr.lower(), r.stderr
    assert json.loads(r.stdout) == {"ok": False, "error": r.stderr.strip()[len("spadscan: error: "):]}


def test_the_help_says_status_takes_json(capsys):
    with pytest.raises(SystemExit) as done:
        main(["ctl", "status", "--help"])
    assert done.value.code == 0
    shown = " ".join(capsys.readouterr().out.split())
    assert "--json the same JSON as without it" in shown and '{"ok": false, "error": ...}' in shown
    assert "`scan_elapsed_s`: seconds since the scan began" in shown
    with pytest.raises(SystemExit):
        main(["ctl", "--help"])
    assert "`status` takes --json too" in " ".join(capsys.readouterr().out.split())
