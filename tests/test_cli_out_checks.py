"""One-line refusals that name what is wrong, before any work: `baseline` and `simulate` check --out as `reconstruct`
does (a folder that cannot be made is refused naming --out, before a calibration of minutes), `worker --root` tells a
root that does not exist from one that is a file, and `ctl --socket` a path that is no socket from a socket nobody
listens on."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import pytest

from spadscan.cli import main

UNMAKEABLE = "/proc/spadscan-test"
"""A folder that no user can create, root included (os.access says yes to root; the real mkdir says no)."""

pytestmark = pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs a Linux /proc")


def one_line_error(capsys) -> str:
    """The command's error line (stderr: one line; stdout: nothing)."""
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1 and "Traceback" not in captured.err, captured
    return captured.err.strip()


@pytest.fixture
def here(tmp_path, monkeypatch) -> Path:
    """The test's folder as the current folder, holding `afile` (a regular file)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("x")
    return tmp_path


@pytest.fixture
def capture(here, capsys) -> str:
    """A small simulated capture, `cap`, with the ground truth it names."""
    assert main(["simulate", "builtin:sphere", "--out", "cap", "--views", "8", "--no-progress"]) == 0
    capsys.readouterr()
    return "cap"


@pytest.fixture
def no_baseline_runs(monkeypatch):
    """Fail the test if the baseline itself (and its calibration) starts."""
    from spadscan.worker.baselines import run

    def ran(*args, **kwargs):
        raise AssertionError("the baseline ran although its --out is refused")

    monkeypatch.setattr(run, "run_baseline", ran)


# ---- baseline --out (defect: --calibrate ran for 37 s, then a bare "Operation not permitted (/sys/nu)") ---------
@pytest.mark.parametrize("out, reason", [(f"{UNMAKEABLE}/nu", "cannot create it ("),
                                         ("afile/x", "afile is a file, not a folder")])
def test_baseline_refuses_an_out_that_cannot_be_made_before_it_runs(here, capture, capsys, no_baseline_runs, out,
                                                                    reason):
    assert main(["baseline", "space-carving", capture, "--out", out, "--calibrate"]) == 1
    err = one_line_error(capsys)
    assert err.startswith(f"spadscan: error: --out {out}: {reason}"), err


# ---- simulate --out (defect: a bare "Operation not permitted (/sys/nu)", not naming --out) ------------------------
@pytest.mark.parametrize("out, reason", [(f"{UNMAKEABLE}/cap", "cannot create it ("),
                                         ("afile/cap", "afile is a file, not a folder")])
def test_simulate_names_out_when_it_cannot_be_made(here, capsys, out, reason):
    assert main(["simulate", "builtin:sphere", "--out", out, "--views", "8", "--no-progress"]) == 1
    err = one_line_error(capsys)
    assert err.startswith(f"spadscan: error: --out {out}: {reason}"), err


# ---- worker --root (defect: a root that does not exist was said to be "not a folder") -----------------------------
def test_worker_says_a_missing_root_does_not_exist_and_a_file_is_not_a_folder(here, capsys):
    os.symlink("gone", "dangling")
    for root in ("nosuch", "dangling"):
        assert main(["worker", "--root", root, "--status"]) == 1
        assert one_line_error(capsys) == f"spadscan: error: {root}: captures root does not exist"
    assert main(["worker", "--root", "afile", "--status"]) == 1
    assert one_line_error(capsys) == "spadscan: error: afile: captures root is not a folder"


# ---- ctl --socket (defect: a regular file was said to have "no daemon listening") ---------------------------------
NOT_A_SOCKET = ("{path} is {what}, not a socket: no daemon listens there (pass --socket the daemon's control socket, "
                "its config's `socket` key)")


@pytest.mark.parametrize("path, what", [("afile", "a file"), (".", "a folder")])
def test_ctl_says_a_path_that_is_no_socket_is_not_a_socket(here, capsys, path, what):
    said = NOT_A_SOCKET.format(path=path, what=what)
    assert main(["ctl", "--socket", path, "status"]) == 1
    assert one_line_error(capsys) == f"spadscan: error: {said}"
    assert main(["ctl", "--socket", path, "status", "--json"]) == 1
    captured = capsys.readouterr()
    assert json.loads(captured.out) == {"ok": False, "error": said} and captured.err == f"spadscan: error: {said}\n"
    assert main(["ctl", "--socket", path, "wait", "x", "--json"]) == 1
    captured = capsys.readouterr()
    line = json.loads(captured.out)
    assert line["error"] == said and line["wait"]["ended"] == "error", line
    assert captured.err == f"spadscan: error: {said}\n"


def test_ctl_still_says_no_daemon_listens_on_a_socket_nobody_serves(sock_dir, capsys):
    path = str(sock_dir / "stale.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.bind(path)
    assert main(["ctl", "--socket", path, "status"]) == 1
    assert one_line_error(capsys).startswith(f"spadscan: error: no daemon is listening on {path}")
