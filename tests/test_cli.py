"""The `spadscan` dispatcher: help, unknown commands, one-line errors and exit codes, lazy imports."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import pytest

from spadscan import __version__
from spadscan.cli import COMMANDS, _available, main, run_command
from spadscan.protocol.errors import CaptureError, SpadscanError

from process_helpers import reaped


def test_help_lists_the_available_commands(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "usage: spadscan" in out
    for name in ("import-lcspc", "eval"):
        assert name in out and COMMANDS[name][1] in out
    for name in COMMANDS:
        assert (f"  {name} " in out) == _available(name)


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "usage: spadscan" in capsys.readouterr().out


def test_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"spadscan {__version__}"


def test_unknown_command_is_one_line(capsys):
    assert main(["scan-everything"]) == 2
    err = capsys.readouterr().err
    assert "unknown command 'scan-everything'" in err and err.count("\n") == 1


def test_command_help_shows_the_module_docstring(capsys):
    with pytest.raises(SystemExit) as info:
        main(["eval", "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert "usage: spadscan eval" in out and "--gt" in out and "Chamfer" in out


def test_spadscan_errors_become_one_line_and_exit_1(capsys):
    def fail(args):
        raise CaptureError("captures/x/scan.json: missing")

    assert run_command(fail, argparse.Namespace()) == 1
    assert capsys.readouterr().err == "spadscan: error: captures/x/scan.json: missing\n"


def test_os_errors_and_interrupts(capsys):
    def missing(args):
        open("/nonexistent/dir/file")

    def interrupted(args):
        raise KeyboardInterrupt

    assert run_command(missing, argparse.Namespace()) == 1
    err = capsys.readouterr().err
    assert err.startswith("spadscan: error:") and "/nonexistent/dir/file" in err and err.count("\n") == 1
    assert run_command(interrupted, argparse.Namespace()) == 130
    assert capsys.readouterr().err == "spadscan: interrupted\n"


def test_success_returns_the_commands_code():
    assert run_command(lambda a: None, argparse.Namespace()) == 0
    assert run_command(lambda a: 3, argparse.Namespace()) == 3


def test_other_exceptions_are_not_hidden():
    # A bug must surface with its traceback, not as a polite one-liner.
    def bug(args):
        raise ZeroDivisionError("bug")

    with pytest.raises(ZeroDivisionError):
        run_command(bug, argparse.Namespace())


def test_a_real_command_error_through_main(tmp_path, capsys):
    assert main(["eval", str(tmp_path / "nope.obj"), "--gt", "builtin:sphere"]) == 1
    err = capsys.readouterr().err
    assert err == f"spadscan: error: {tmp_path / 'nope.obj'}: no such mesh file\n"
    assert issubclass(CaptureError, SpadscanError)


def test_console_script_end_to_end(tmp_path):
    """The installed entry point: exit codes and one-line stderr, in a fresh process."""
    exe = [sys.executable, "-m", "spadscan.cli"]
    ok = subprocess.run(exe + ["--help"], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and "commands:" in ok.stdout
    bad = subprocess.run(exe + ["eval", str(tmp_path / "x.stl"), "--gt", "builtin:cup"], capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 1 and bad.stderr.count("\n") == 1 and "Traceback" not in bad.stderr


def test_command_modules_import_nothing_heavy():
    """Importing a command and building its parser must not import torch or trimesh (`ctl status` stays fast)."""
    names = [COMMANDS[n][0] for n in COMMANDS if _available(n)]
    code = (
        "import argparse, importlib, json, sys\n"
        f"for name in {names!r}:\n"
        "    m = importlib.import_module('spadscan.commands.' + name)\n"
        "    m.add_arguments(argparse.ArgumentParser())\n"
        "print(json.dumps(sorted(k for k in ('torch', 'trimesh', 'scipy') if k in sys.modules)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == []


# ---- operating-system errors: full disks, files in the way, closed pipes ----------------------------------------
def _fail_with(exc):
    def fail(args):
        raise exc

    return fail


@pytest.mark.parametrize("exc", [
    OSError(28, "No space left on device", "cap/.tmp-chunk-000001/hists.npy"),
    OSError(122, "Disk quota exceeded", "cap/.tmp-chunk-000001/hists.npy"),
])
def test_a_full_disk_is_one_line_naming_the_path(capsys, exc):
    assert run_command(_fail_with(exc), argparse.Namespace()) == 1
    assert capsys.readouterr().err == ("spadscan: error: cap/.tmp-chunk-000001/hists.npy: the disk is full (no space "
                                       "left on the device); free some space or write elsewhere\n")


def test_numpys_short_write_is_a_full_disk(capsys):
    # np.save on a full disk: no errno, no filename, only "N requested and M written"
    assert run_command(_fail_with(OSError("8192 requested and 3040 written")), argparse.Namespace()) == 1
    err = capsys.readouterr().err
    assert err.startswith("spadscan: error: the disk is full") and err.count("\n") == 1


def test_a_file_where_a_folder_is_needed(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("x")

    def mkdir(path):
        return lambda args: __import__("pathlib").Path(path).mkdir(parents=True, exist_ok=True)

    assert run_command(mkdir("afile"), argparse.Namespace()) == 1
    assert capsys.readouterr().err == "spadscan: error: afile: exists and is not a folder\n"
    assert run_command(mkdir("afile/sub/deeper"), argparse.Namespace()) == 1
    assert capsys.readouterr().err == ("spadscan: error: afile: is a file, not a folder (needed for "
                                       "afile/sub/deeper)\n")


@pytest.mark.parametrize("command", [["reconstruct", "cap"], ["simulate", "builtin:sphere", "--views", "4"],
                                     ["baseline", "reprojection", "cap"]])
def test_out_pointing_at_a_file_through_main(tmp_path, capsys, monkeypatch, command):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("x")
    if command[0] != "simulate":
        assert main(["simulate", "builtin:sphere", "--views", "4", "--out", "cap", "--no-progress"]) == 0
        capsys.readouterr()
    assert main([*command, "--out", "afile"]) == 1
    err = capsys.readouterr().err
    # (simulate, whose --out is checked as a folder to make, names the option too)
    said = "spadscan: error: --out afile: " if command[0] == "simulate" else "spadscan: error: afile: "
    assert err.startswith(said) and "not a folder" in err and err.count("\n") == 1
    assert (tmp_path / "afile").read_text() == "x"


def test_a_closed_output_pipe_ends_quietly():
    """`spadscan ctl status | head -1`: the reader has what it wanted; no error, no traceback at exit."""
    code = ("import sys\n"
            "from spadscan.cli import run_command\n"
            "def lines(args):\n"
            "    for i in range(200000):\n"
            "        print('line', i)\n"
            "sys.exit(run_command(lines, None))\n")
    with reaped(subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE)) as (proc,):
        assert proc.stdout.readline() == b"line 0\n"
        proc.stdout.close()
        err = proc.stderr.read().decode()
        assert proc.wait(timeout=120) == 141 and err == ""


def test_version_into_a_closed_pipe_ends_quietly():
    """`spadscan --version` whose reader closed its end first: no traceback, the status of a SIGPIPE."""
    code = "import sys; from spadscan.cli import main; sys.exit(main(['--version']))"
    read, write = os.pipe()
    os.close(read)  # the reader is gone before anything is written
    with reaped(subprocess.Popen([sys.executable, "-c", code], stdout=write, stderr=subprocess.PIPE)) as (proc,):
        os.close(write)
        err = proc.stderr.read().decode()
        assert proc.wait(timeout=120) == 141 and err == "", err


def test_a_broken_pipe_elsewhere_is_still_an_error(capsys):
    """A BrokenPipeError while stdout is still read (a socket, a child's pipe) is an error like any other."""
    code = ("import sys\n"
            "from spadscan.cli import run_command\n"
            "def fail(args):\n"
            "    print('partial')\n"
            "    raise BrokenPipeError(32, 'Broken pipe')\n"
            "sys.exit(run_command(fail, None))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and proc.stderr == "spadscan: error: Broken pipe\n"
    assert run_command(_fail_with(BrokenPipeError(32, "Broken pipe")), argparse.Namespace()) == 1  # captured stdout
    assert capsys.readouterr().err == "spadscan: error: Broken pipe\n"


def test_a_list_of_numbers_that_starts_negative_is_a_flags_value(tmp_path, capsys):
    """`--plane -1,0,0,0,0,1` reaches the command (here: which says the capture is missing), not argparse's
    'expected one argument'."""
    missing = tmp_path / "no-capture"
    for flag, value in (("--plane", "-1,0,0,0,0,1"), ("--sphere", "-0.1,.2,-3e-2,0.05")):
        assert main(["calibrate", "hand-eye", str(missing), flag, value]) == 1
        err = capsys.readouterr().err
        assert err.startswith("spadscan: error: ") and "no-capture" in err and "expected one argument" not in err
