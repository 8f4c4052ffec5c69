"""The `spadscan` dispatcher: help, unknown commands, one-line errors and exit codes, lazy imports."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from spadscan import __version__
from spadscan.cli import COMMANDS, _available, main, run_command
from spadscan.protocol.errors import CaptureError, SpadscanError


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
