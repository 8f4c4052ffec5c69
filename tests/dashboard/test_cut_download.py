"""A served file cut short after its headers (the live mesh truncated or unreadable mid-download) reaches the client
as a failed download, a body shorter than its Content-Length, never as a whole-looking file; the server answers the
next request."""

from __future__ import annotations

import errno
import http.client
import os
import pathlib

import pytest

from dashboard_helpers import complete_scan, serving, status
from spadscan.dashboard.server import BLOCK

SIZE = 4 * BLOCK
"""A live mesh of several blocks: the server has sent part of it when the cut comes."""


def live_mesh(root: pathlib.Path) -> pathlib.Path:
    complete_scan(root / "mug", 1)
    live = root / "mug" / "recon" / "live"
    live.mkdir(parents=True)
    mesh = live / "mesh.ply"
    mesh.write_bytes(b"m" * SIZE)
    return mesh


class CutAfterFirstBlock:
    """A served file's reader that hands out its first block, then `cut()`s (the headers and that block are sent)."""

    def __init__(self, f, cut):
        self.f, self.cut, self.reads = f, cut, 0

    def read(self, n=-1):
        self.reads += 1
        if self.reads == 2:
            self.cut(self.f)
        return self.f.read(n)

    def __getattr__(self, name):
        return getattr(self.f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()


def truncated(f):
    os.truncate(f.name, BLOCK + 10)  # the worker rewrote the file in place (a copy tool, a hand edit)


def unreadable(f):
    raise OSError(errno.EIO, os.strerror(errno.EIO))


@pytest.mark.parametrize("cut", [truncated, unreadable])
def test_a_live_mesh_cut_short_after_its_headers_is_a_failed_download(tmp_path, monkeypatch, cut):
    mesh = live_mesh(tmp_path)
    real_open = pathlib.Path.open

    def cut_open(self, *args, **kwargs):
        f = real_open(self, *args, **kwargs)
        return CutAfterFirstBlock(f, cut) if self == mesh else f

    monkeypatch.setattr(pathlib.Path, "open", cut_open)
    with serving(tmp_path) as server:
        conn = http.client.HTTPConnection(*server.server_address[:2], timeout=30)
        try:
            conn.request("GET", "/files/mug/recon/live/mesh.ply")
            answer = conn.getresponse()
            assert answer.status == 200
            assert int(answer.getheader("Content-Length")) == SIZE
            with pytest.raises(http.client.IncompleteRead) as cut_short:
                answer.read()
            assert len(cut_short.value.partial) < SIZE
        finally:
            conn.close()
        assert status(server)["scans"][0]["name"] == "mug"  # the server goes on
