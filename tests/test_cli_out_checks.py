"""One-line refusals that name what is wrong, before any work: `baseline` and `simulate` check --out as `reconstruct`
does (a folder that cannot be made is refused naming --out, before a calibration of minutes), `worker --root` tells a
root that does not exist from one that is a file, and `ctl --socket` a path that is no socket from a socket nobody
listens on."""

from __future__ import annotations

import builtins
import errno
import json
import os
import shutil
import socket
import subprocess
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


# ---- an --out folder that cannot be written into (defect: simulate said a bare "Operation not permitted
# (rotest/schedule.npy)", baseline the same after its run, reconstruct after its first lines; now one line as
# reconstruct's own, before any work) ----------------------------------------------------------------------------------
SWEEP = """
[sweep]
scenes = ["builtin:sphere"]
presets = ["fast"]
baselines = []
[base]
views = 8
rays_per_zone = 256
"""


def immutable(folder: Path) -> None:
    """Make `folder` immutable (chattr +i: root cannot write into it either; the caller undoes it); skips where the
    filesystem or the process cannot."""
    chattr = shutil.which("chattr")
    if chattr is None or subprocess.run([chattr, "+i", str(folder)], capture_output=True).returncode != 0:
        pytest.skip("no immutable folders here (chattr +i refused)")
    try:
        (folder / "probe").write_text("x")
    except OSError:
        return
    (folder / "probe").unlink()
    subprocess.run([chattr, "-i", str(folder)], check=True)
    pytest.skip("chattr +i did not stop writes here")


def refused_writes(folder: Path, monkeypatch) -> None:
    """Make the calls that create or write files and folders refuse `folder`'s contents as an immutable folder does
    (EPERM), whoever the process runs as."""
    inside = str(folder.resolve())

    def blocked(path) -> bool:
        return os.path.dirname(os.path.abspath(os.fspath(path))) == inside

    def refuse(path):
        raise PermissionError(errno.EPERM, os.strerror(errno.EPERM), os.fspath(path))

    real_mkdir, real_open, real_os_open = os.mkdir, builtins.open, os.open
    real_rename, real_replace = os.rename, os.replace

    def mkdir(path, *args, **kwargs):
        return refuse(path) if blocked(path) else real_mkdir(path, *args, **kwargs)

    def open_(file, mode="r", *args, **kwargs):
        writes = isinstance(file, (str, os.PathLike)) and any(c in mode for c in "wax+")
        return refuse(file) if writes and blocked(file) else real_open(file, mode, *args, **kwargs)

    def os_open(path, flags, *args, **kwargs):
        writes = flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT)
        return refuse(path) if writes and blocked(path) else real_os_open(path, flags, *args, **kwargs)

    def rename(src, dst, *args, **kwargs):
        return refuse(dst) if blocked(dst) else real_rename(src, dst, *args, **kwargs)

    def replace(src, dst, *args, **kwargs):
        return refuse(dst) if blocked(dst) else real_replace(src, dst, *args, **kwargs)

    for name, fake in (("mkdir", mkdir), ("open", os_open), ("rename", rename), ("replace", replace)):
        monkeypatch.setattr(os, name, fake)
    monkeypatch.setattr(builtins, "open", open_)


@pytest.fixture(params=["immutable", "patched"])
def rotest(request, here, monkeypatch) -> str:
    """`rotest`, an existing folder this process cannot write into: immutable, or refused by patched os calls."""
    folder = here / "rotest"
    folder.mkdir()
    if request.param == "immutable":
        immutable(folder)
        request.addfinalizer(lambda: subprocess.run([shutil.which("chattr"), "-i", str(folder)], check=True))
    else:
        refused_writes(folder, monkeypatch)
    return "rotest"


def test_simulate_says_an_out_it_cannot_write_into_as_the_others_do(rotest, capsys):
    assert main(["simulate", "builtin:sphere", "--out", rotest, "--views", "8", "--no-progress"]) == 1
    assert one_line_error(capsys).startswith(f"spadscan: error: --out {rotest}: cannot write into it (")


def test_baseline_refuses_an_out_it_cannot_write_into_before_it_runs(rotest, capture, capsys, no_baseline_runs):
    assert main(["baseline", "space-carving", capture, "--out", rotest, "--calibrate"]) == 1
    assert one_line_error(capsys).startswith(f"spadscan: error: --out {rotest}: cannot write into it (")


def test_reconstruct_refuses_an_out_it_cannot_write_into_before_it_says_anything(rotest, capture, capsys):
    assert main(["reconstruct", capture, "--out", rotest, "--steps", "1", "--no-progress"]) == 1
    assert one_line_error(capsys).startswith(f"spadscan: error: --out {rotest}: cannot write into it (")
    assert os.listdir(rotest) == []


@pytest.mark.parametrize("dry_run", [[], ["--dry-run"]])
def test_sweep_refuses_an_out_it_cannot_write_into_before_its_plan(rotest, here, capsys, dry_run):
    """Said before the plan's line, as the others say it (not "Read-only file system (rotest/.lock)" after it)."""
    (here / "s.toml").write_text(SWEEP)
    assert main(["sweep", "s.toml", "--out", rotest, "--workers", "1", "--no-progress", *dry_run]) == 1
    assert one_line_error(capsys).startswith(f"spadscan: error: --out {rotest}: cannot write into it (")
    assert os.listdir(rotest) == []


def test_import_lcspc_refuses_an_out_it_cannot_write_into_before_it_reads(rotest, here, capsys):
    (here / "s.json").write_text("[]")  # never read: --out is refused first
    assert main(["import-lcspc", "s.json", "--out", rotest, "--no-progress"]) == 1
    assert one_line_error(capsys).startswith(f"spadscan: error: --out {rotest}: cannot write into it (")
    assert os.listdir(rotest) == []


def test_a_worker_refuses_a_queue_it_cannot_write_into_and_status_still_reads_it(rotest, here, capsys):
    """A run writes its jobs into the queue, and --redo and --retry-failed the jobs they queue again: refused, naming
    --queue, as --out is; --status only reads it."""
    (here / "caps").mkdir()
    for action in (["--once"], ["--redo", "s-fast"], ["--retry-failed"]):
        assert main(["worker", "--root", "caps", "--queue", rotest, *action]) == 1
        assert one_line_error(capsys).startswith(f"spadscan: error: --queue {rotest}: cannot write into it ("), action
    assert main(["worker", "--root", "caps", "--queue", rotest, "--status"]) == 0
    assert f"no jobs in {rotest}" in capsys.readouterr().out
    assert os.listdir(rotest) == []


# ---- reconstruct: options before folders (defect: --out holding a result was refused first; once --overwrite was
# given, a bad --threads, and then a bad --set, each in turn) ------------------------------------------------------
def test_reconstruct_checks_its_options_before_its_folders(here, capsys):
    (here / "cap").mkdir()
    (here / "cap" / "scan.json").write_text("{}")  # a capture folder to the checks; its reading fails later
    (here / "result").mkdir()
    (here / "result" / "mesh.ply").write_text("an earlier result")
    base = ["reconstruct", "cap", "--out", "result", "--no-progress"]
    assert main([*base, "--threads", "0", "--set", "nonsense"]) == 1
    assert one_line_error(capsys) == "spadscan: error: threads 0 must be an integer in [1, 1024]"
    assert main([*base, "--threads", "1", "--set", "nonsense"]) == 1
    assert "config override 'nonsense' must look like KEY=VALUE" in one_line_error(capsys)
    assert main([*base, "--threads", "1", "--set", "field.nonsense=2"]) == 1
    assert "config override 'field.nonsense': no field 'nonsense'" in one_line_error(capsys)
    assert main([*base, "--threads", "1", "--set", "field.resolution=48"]) == 1
    assert "result: already holds a result (mesh.ply)" in one_line_error(capsys)
    assert (here / "result" / "mesh.ply").read_text() == "an earlier result"


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
