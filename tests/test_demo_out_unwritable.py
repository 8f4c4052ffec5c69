"""`spadscan demo --out DIR` where DIR is there but cannot be written into says so in one line that names --out, as
the other commands say it (`--out DIR: cannot write into it (...)`), not as an OS error about its logs folder; before
the banner, and without starting anything."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from spadscan.cli import main
from spadscan.demo import DemoOptions, Processes, make_out


@pytest.fixture
def nothing_starts(monkeypatch):
    """Fail the test if the demo starts a process."""
    def start(self, name, argv, log):
        raise AssertionError(f"the demo started {name} although its --out cannot be written")

    monkeypatch.setattr(Processes, "start", start)


@pytest.fixture
def unwritable(tmp_path):
    """A folder this process cannot write into, for real: mode 555 for a user, immutable for root (whom the mode does
    not stop); skipped where neither can be had."""
    folder = tmp_path / "D"
    folder.mkdir()
    if os.geteuid() != 0:
        folder.chmod(0o555)
        yield folder
        folder.chmod(0o755)
        return
    chattr = shutil.which("chattr")
    made = chattr is not None and subprocess.run([chattr, "+i", str(folder)], capture_output=True).returncode == 0
    if not made:
        pytest.skip("root without an immutable folder (chattr +i): the patched test below covers it")
    try:
        yield folder
    finally:
        subprocess.run([chattr, "-i", str(folder)], check=True)


def test_an_out_that_cannot_be_written_into_is_refused_in_one_line_naming_it(unwritable, capsys, nothing_starts):
    assert main(["demo", "--out", str(unwritable)]) == 1
    captured = capsys.readouterr()
    assert captured.out == "" and "Traceback" not in captured.err, captured
    (line,) = captured.err.splitlines()  # no banner naming a logs folder that cannot be made
    assert line.startswith(f"spadscan: error: --out {unwritable}: cannot write into it ("), line
    assert list(unwritable.iterdir()) == []


def test_the_demos_folders_are_refused_as_the_other_commands_refuse_them(tmp_path, monkeypatch):
    """Through the function, the OS refusing every folder made inside DIR (a read-only mount, say)."""
    from spadscan.protocol.errors import SpadscanError

    folder = tmp_path / "D"
    folder.mkdir()
    real_mkdir = os.mkdir

    def mkdir(path, *args, **kwargs):
        if Path(path).parent == folder:
            raise PermissionError(errno.EPERM, os.strerror(errno.EPERM), str(path))
        return real_mkdir(path, *args, **kwargs)

    monkeypatch.setattr(os, "mkdir", mkdir)
    with pytest.raises(SpadscanError) as refused:
        make_out(DemoOptions(out=folder))
    assert str(refused.value) == f"--out {folder}: cannot write into it (Operation not permitted)"
    assert list(folder.iterdir()) == []
    # A folder that is not there and cannot be made is named too, as `check_folder_option` names it for the others.
    with pytest.raises(SpadscanError, match=r"^--out .*/D/new: cannot create it \("):
        make_out(DemoOptions(out=folder / "new"))
