"""The daemon's way out of a scan it could not take over (damaged_chunks) and the reader's refusal to load a capture
(CaptureReader.load) tell whole, damaged and unreadable-by-this-user chunks apart the same way: the advice to move a
chunk out must name exactly the chunks the reader refuses, and never one whose content may be intact."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from spadscan.daemon.scan_job import damaged_chunks
from spadscan.protocol.capture_format import Measurement, NoPermission, chunk_name
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter
from spadscan.protocol.errors import CaptureError
from spadscan.protocol.sensor_presets import sensor_preset

from disk_faults import deny_open, fail_lookup

TMF = sensor_preset("tmf8820")


def write(path: Path, n: int, chunk_size: int) -> None:
    """A complete capture of n measurements (one per pose), with reference histograms."""
    with CaptureWriter.create(path, TMF, chunk_size=chunk_size) as w:
        for i in range(n):
            hist = np.full((TMF.n_zones, TMF.n_bins), i + 1, np.uint32)
            pose = np.eye(4)
            pose[:3, 3] = [0.5, 0.01 * i, 0.0]
            w.append(Measurement(hist=hist, pose=pose, pose_index=i, frame=0,
                                 reference=np.ones(TMF.n_bins, np.uint32)))
        w.finish()


def test_the_chunks_the_daemon_says_to_move_out_are_those_the_reader_refuses(tmp_path, monkeypatch):
    """A torn file and a file that cannot even be looked up (an I/O error): both chunks are damaged for both."""
    path = tmp_path / "scan"
    write(path, 8, 2)  # four chunks
    (path / chunk_name(1) / "hists.npy").write_bytes(b"")
    fail_lookup(monkeypatch, path / chunk_name(2) / "reference.npy")
    names, damaged, forbidden = damaged_chunks(path)
    assert names == [chunk_name(k) for k in range(4)]
    assert damaged == [chunk_name(1), chunk_name(2)] and forbidden == []
    with pytest.raises(CaptureError) as refused:
        CaptureReader(path).load()
    said = str(refused.value)
    assert f"; 2 of 4 chunks cannot be read ({', '.join(damaged)}): moving them out of {path}" in said, said
    assert "\n" not in said


def test_a_chunk_this_user_may_not_read_is_not_damaged_for_either(tmp_path, monkeypatch):
    path = tmp_path / "scan"
    write(path, 6, 2)
    (path / chunk_name(0) / "meta.json").write_text("{")
    deny_open(monkeypatch, path / chunk_name(1) / "hists.npy")
    _, damaged, forbidden = damaged_chunks(path)
    assert damaged == [chunk_name(0)] and forbidden == [chunk_name(1)]
    with pytest.raises(NoPermission) as refused:
        CaptureReader(path).load()
    assert str(refused.value).startswith(f"{path / chunk_name(1) / 'hists.npy'}: cannot be read (permission denied")
