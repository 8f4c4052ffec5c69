"""What the dashboard's server serves under /files/ and /live3d/, asked as a browser would: a link inside the root
leads into no hidden folder; a file is streamed, never read whole (the root holds chunk data and meshes of hundreds
of MB), HEAD included; a file gone or unreadable gets an answer that says so; the 3D view is of the root's own scans
only, and the server keeps few of those pages."""

from __future__ import annotations

import errno
import http.client
import os
import pathlib
import tracemalloc

import trimesh

from dashboard_helpers import complete_scan, get, serving, status
import spadscan.dashboard.server as server_module

BIG = 64 * 2**20  # a mesh or chunk of the kind an operator's root holds


def request(server, method: str, path: str) -> tuple[int, dict, bytes]:
    conn = http.client.HTTPConnection(*server.server_address[:2], timeout=30)
    try:
        conn.request(method, path)
        answer = conn.getresponse()
        return answer.status, dict(answer.getheaders()), answer.read()
    finally:
        conn.close()


def test_a_link_inside_the_root_leads_into_no_hidden_folder_nor_out_of_the_root(tmp_path):
    root = tmp_path / "captures"
    complete_scan(root / "mug", 1)
    (root / ".queue" / "logs").mkdir(parents=True)
    (root / ".queue" / "logs" / "secret.log").write_text("queue internals\n")
    (tmp_path / "outside.txt").write_text("not the root's\n")
    os.symlink(root / ".queue", root / "mug" / "q")  # a folder link
    os.symlink(root / ".queue" / "logs" / "secret.log", root / "mug" / "log.txt")  # a file link
    os.symlink(tmp_path / "outside.txt", root / "mug" / "out.txt")
    (root / "mug" / "notes.txt").write_text("the scan's own\n")
    with serving(root) as server:
        for path in ("/files/mug/q/logs/secret.log", "/files/mug/log.txt", "/files/mug/out.txt"):
            assert get(server, path) == (404, b"not found\n"), path
        assert get(server, "/files/mug/notes.txt") == (200, b"the scan's own\n")


def test_a_large_file_is_streamed_and_a_head_request_reads_none_of_it(tmp_path):
    complete_scan(tmp_path / "mug", 1)
    big = tmp_path / "mug" / "recon" / "big.bin"
    big.parent.mkdir()
    with open(big, "wb") as f:
        f.truncate(BIG)  # sparse: costs no disk
        f.seek(BIG - 5)
        f.write(b"tail!")
    with serving(tmp_path) as server:
        tracemalloc.start()  # every thread's allocations: the server's included
        try:
            code, headers, body = request(server, "HEAD", "/files/mug/recon/big.bin")
            head_peak = tracemalloc.get_traced_memory()[1]
            assert (code, headers["Content-Length"], body) == (200, str(BIG), b"")
            tracemalloc.reset_peak()
            conn = http.client.HTTPConnection(*server.server_address[:2], timeout=60)
            conn.request("GET", "/files/mug/recon/big.bin")
            answer = conn.getresponse()
            assert answer.status == 200 and answer.getheader("Content-Length") == str(BIG)
            got, last = 0, b""
            while block := answer.read(1 << 20):
                got, last = got + len(block), (last + block)[-5:]
            conn.close()
            get_peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert (got, last) == (BIG, b"tail!")
    assert head_peak < BIG // 8, f"a HEAD request took {head_peak >> 20} MB"
    assert get_peak < BIG // 8, f"serving a {BIG >> 20} MB file took {get_peak >> 20} MB"


def test_a_file_removed_after_it_was_found_is_not_found_and_the_server_goes_on(tmp_path, monkeypatch):
    complete_scan(tmp_path / "mug", 1)
    gone = tmp_path / "mug" / "gone.txt"
    gone.write_text("soon gone\n")
    found = server_module.safe_path

    def then_removed(root, rel):  # the worker removes it between the server's check and its reading
        path = found(root, rel)
        if path is not None and path.name == "gone.txt":
            path.unlink()
        return path

    monkeypatch.setattr(server_module, "safe_path", then_removed)
    with serving(tmp_path) as server:
        assert get(server, "/files/mug/gone.txt") == (404, b"not found\n")
        assert status(server)["scans"][0]["name"] == "mug"


def test_a_file_the_disk_cannot_read_is_answered_with_why(tmp_path, monkeypatch):
    # A disk error (EIO) is an OSError like any other: the operator is told, the request is answered, and the
    # server answers the next one.
    complete_scan(tmp_path / "mug", 1)
    (tmp_path / "mug" / "bad.txt").write_text("on a failing sector\n")
    real_open = pathlib.Path.open

    def failing_open(self, *args, **kwargs):
        if self.name == "bad.txt":
            raise OSError(errno.EIO, os.strerror(errno.EIO), str(self))
        return real_open(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "open", failing_open)
    with serving(tmp_path) as server:
        code, body = get(server, "/files/mug/bad.txt")
        assert code == 503 and b"Input/output error" in body, (code, body)
        assert status(server)["scans"][0]["name"] == "mug"


def live_mesh(scan_path) -> None:
    live = scan_path / "recon" / "live"
    live.mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=1, radius=0.05).export(live / "mesh.ply")


def test_the_3d_view_is_of_a_scan_of_the_root_never_of_a_folder_nested_in_one(tmp_path):
    # a capture copied into a folder under the root (an operator's "old/" folder) is no scan of this root: the page
    # never links its live view, and the server does not make one
    complete_scan(tmp_path / "mug", 1)
    live_mesh(tmp_path / "mug")
    complete_scan(tmp_path / "old" / "vase", 1)
    live_mesh(tmp_path / "old" / "vase")
    with serving(tmp_path) as server:
        assert get(server, "/live3d/mug")[0] == 200
        for path in ("/live3d/old/vase", "/live3d/old%2Fvase", "/live3d/old/vase/"):
            assert get(server, path) == (404, b"not found\n"), path
        assert [s["name"] for s in status(server)["scans"]] == ["mug"]


def test_the_server_keeps_the_3d_views_of_a_few_scans_not_of_every_scan_ever_shown(tmp_path):
    names = [f"scan{i}" for i in range(8)]
    for name in names:
        complete_scan(tmp_path / name, 1)
        live_mesh(tmp_path / name)
    with serving(tmp_path) as server:
        views = server.RequestHandlerClass.keywords["live"]
        for name in names:
            code, page = get(server, f"/live3d/{name}")
            assert code == 200 and f"{name} (live)".encode() in page, name
        kept = views.kept()
        assert 0 < len(kept) <= 4, kept
        assert kept[-1].parts[-4] == names[-1], "the view last asked for is the one kept"
        # one removed since: its view answers not found
        (tmp_path / names[-1] / "recon" / "live" / "mesh.ply").unlink()
        assert get(server, f"/live3d/{names[-1]}") == (404, b"not found\n")
