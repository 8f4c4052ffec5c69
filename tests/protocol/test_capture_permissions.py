"""A capture file this user may not read is named as such, never as damaged: the advice for a damaged chunk (move it
out of the scan folder) would throw away good data.

The permission error is raised at the open call (monkeypatch): as root, chmod 000 does not stop a read, and these
tests must hold whoever runs them."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from spadscan.cli import main
from spadscan.protocol.capture_format import MANIFEST, NoPermission, chunk_name, read_json, read_npy
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.errors import CaptureError

from disk_faults import deny_open
from test_capture import write


def deny_read_text(monkeypatch, denied: Path) -> None:
    """Make read_json's read of `denied` fail with EACCES."""
    read_text = Path.read_text

    def guarded_read_text(self, *args, **kwargs):
        if os.fspath(self) == os.fspath(denied):
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(self))
        return read_text(self, *args, **kwargs)

    monkeypatch.setattr(Path, "read_text", guarded_read_text)


@pytest.mark.parametrize("name", ["hists.npy", "poses.npy"])
def test_an_unreadable_chunk_array_says_permission_denied_not_corrupt(tmp_path, monkeypatch, name):
    path = tmp_path / "scan"
    write(path, 3, 3)
    denied = path / chunk_name(0) / name
    deny_open(monkeypatch, denied)
    with pytest.raises(NoPermission) as info:
        CaptureReader(path).read_chunk(chunk_name(0))
    message = str(info.value)
    assert message.startswith(f"{denied}: cannot be read (permission denied"), message
    assert "corrupt" not in message and "truncated" not in message and "damaged" not in message, message
    assert "\n" not in message
    assert isinstance(info.value, CaptureError)  # every caller that handles a capture error handles it


def test_an_unreadable_json_file_says_permission_denied(tmp_path, monkeypatch):
    path = tmp_path / "scan"
    write(path, 3, 3)
    denied = path / chunk_name(0) / "meta.json"
    deny_read_text(monkeypatch, denied)
    with pytest.raises(NoPermission) as info:
        read_json(denied)
    assert str(info.value).startswith(f"{denied}: cannot be read (permission denied"), str(info.value)
    assert "unreadable JSON" not in str(info.value)


def test_a_folder_where_an_npy_belongs_is_named_a_folder(tmp_path):
    folder = tmp_path / "hists.npy"
    folder.mkdir()
    with pytest.raises(CaptureError) as info:
        read_npy(folder)
    assert str(info.value) == f"{folder}: a folder, not a .npy file"


def test_damage_is_still_called_damage(tmp_path):
    """The permission branch takes only permission errors: a truncated file is still named corrupt."""
    good = tmp_path / "a.npy"
    np.save(good, np.zeros((4, 4)))
    short = tmp_path / "b.npy"
    short.write_bytes(good.read_bytes()[:-8])
    with pytest.raises(CaptureError) as info:
        read_npy(short)
    assert not isinstance(info.value, NoPermission)
    assert "corrupt or truncated .npy" in str(info.value)


def test_the_cli_names_an_unreadable_chunk_in_one_line(tmp_path, monkeypatch, capsys):
    """What the review saw from reconstruct, baseline and calibrate: the command's one error line."""
    path = tmp_path / "scan"
    write(path, 6, 3)
    assert (path / MANIFEST).is_file()
    denied = path / chunk_name(1) / "hists.npy"
    deny_open(monkeypatch, denied)
    rc = main(["calibrate", "hand-eye", str(path), "--plane", "0,0,0,0,0,1"])
    err = capsys.readouterr().err.strip()
    assert rc == 1, err
    assert err == (f"spadscan: error: {denied}: cannot be read (permission denied: check the file's owner and mode; "
                   f"its content may be intact)"), err
