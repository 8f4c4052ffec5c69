"""Serving a captures root from a test, and asking it exactly what a browser would."""

from __future__ import annotations

import ctypes.util
import http.client
import json
import os
import threading
from contextlib import contextmanager

import pytest

from page_helpers import add_pose, start_scan
from spadscan.dashboard.server import make_server
from spadscan.worker.report.offscreen import OffscreenUnavailable, check_offscreen


@contextmanager
def serving(root, **kwargs):
    server = make_server(root, "127.0.0.1", 0, **kwargs)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        yield server
    finally:
        server.shutdown()
        server.server_close()
        thread.join(10)


OPENGL_WINDOW = "VTK_DEFAULT_OPENGL_WINDOW"
"""The variable the product's off-screen check sets to pick VTK's window (worker/report/offscreen.py)."""


def skip_where_no_off_screen_drawing(monkeypatch) -> None:
    """Skips the test, saying why and what to install, where this machine cannot draw meshes off screen (no display,
    no EGL, no OSMesa): for a test that needs what the worker's own writers draw (a report's 3D view). The product's
    own check decides, as the worker tests' `draws_off_screen` fixture does; the variable it sets is put back after
    the test."""
    keep_opengl_window(monkeypatch)
    try:
        check_offscreen()
    except OffscreenUnavailable as exc:
        pytest.skip(str(exc))


def without_off_screen_opengl(monkeypatch) -> None:
    """This process as the product sees a machine without a display, EGL or OSMesa (offscreen.check_offscreen asks
    the environment and ctypes.util.find_library): the no-OpenGL path, tested on a machine that has one. Undone after
    the test."""
    keep_opengl_window(monkeypatch)
    for name in ("DISPLAY", "WAYLAND_DISPLAY", OPENGL_WINDOW):
        monkeypatch.delenv(name, raising=False)
    find = ctypes.util.find_library
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None if name in ("EGL", "OSMesa") else find(name))


def keep_opengl_window(monkeypatch) -> None:
    """VTK's window variable as it is now, put back after the test (the off-screen check sets it)."""
    if OPENGL_WINDOW in os.environ:
        monkeypatch.setenv(OPENGL_WINDOW, os.environ[OPENGL_WINDOW])
    else:
        monkeypatch.delenv(OPENGL_WINDOW, raising=False)


def get(server, path: str) -> tuple[int, bytes]:
    """GET `path` exactly as given (no client-side normalisation of '..')."""
    conn = http.client.HTTPConnection(*server.server_address[:2], timeout=30)
    try:
        conn.putrequest("GET", path, skip_accept_encoding=True)
        conn.endheaders()
        answer = conn.getresponse()
        return answer.status, answer.read()
    finally:
        conn.close()


def status(server) -> dict:
    code, body = get(server, "/api/status")
    assert code == 200
    return json.loads(body)


def complete_scan(path, poses: int = 3):
    writer, planned = start_scan(path, poses)
    for i in range(poses):
        add_pose(writer, planned, i)
    writer.finish()


def scan_with_non_finite_results(scan_path, steps: int | None = None) -> None:
    """A complete scan whose final report and live status hold an infinity and a NaN (damaged files: spadscan's own
    writers never write them, json.loads reads them); `steps`: the live status's step count, when given."""
    complete_scan(scan_path, 2)
    final = scan_path / "recon" / f"{scan_path.name}-fast"
    final.mkdir(parents=True)
    (final / "report.json").write_text('{"preset": "fast", "chamfer_mm": Infinity, "seconds": NaN}')
    live = scan_path / "recon" / "live"
    live.mkdir()
    steps_field = "" if steps is None else f'"steps": {steps}, '
    (live / "status.json").write_text('{"views_used": 3, ' + steps_field + '"chamfer_mm": NaN}')


def add_final_recon(scan_path, job: str = "job #1?") -> dict[str, bytes]:
    """A finished reconstruction of the scan at `scan_path`, with a report and a (real, 4x4) preview; returns what
    each of those files holds."""
    import io

    import matplotlib.image
    import numpy as np

    recon = scan_path / "recon" / job
    recon.mkdir(parents=True)
    preview = io.BytesIO()
    matplotlib.image.imsave(preview, np.full((4, 4, 3), 0.5), format="png")
    files = {"report.html": f"<p>report of {scan_path.name}</p>".encode(errors="surrogateescape"),
             "preview.png": preview.getvalue()}
    (recon / "report.json").write_text(json.dumps({"preset": "fast", "chamfer_mm": 1.0}))
    for name, data in files.items():
        (recon / name).write_bytes(data)
    return files


def queue_with_a_kept_result_and_a_damaged_record(root) -> dict[str, str]:
    """A queue of two done jobs under `root`: one whose result was already there when it was claimed (kept, not run),
    one with a damaged attempt record. Returns what `spadscan worker --status` says of each in its last column."""
    from spadscan.worker.jobs import Job
    from spadscan.worker.queue import Queue

    queue = Queue.for_root(root)
    for job_id, kept in (("kept-fast", True), ("torn-fast", False)):
        queue.enqueue(Job(id=job_id, scan=job_id.split("-")[0]))
        (root / "results" / job_id).mkdir(parents=True)
        queue.finish(queue.claim(), result=str(root / "results" / job_id), kept=kept)
    (queue.path / "attempts" / "torn-fast" / "zz-torn.json").write_text('{"tok')  # a record torn by a power cut
    return {"kept-fast": f"{root / 'results' / 'kept-fast'} (already there when the job was claimed: kept, not run)",
            "torn-fast": f"{root / 'results' / 'torn-fast'}; unreadable attempt record "
                         f"{queue.path / 'attempts' / 'torn-fast' / 'zz-torn.json'}"}


def preview_png(rows: int = 2) -> bytes:
    """A preview picture as the worker draws one (four angles side by side, 280 pixels each; a row for the
    reconstruction and one for the ground truth), in grey."""
    import io

    import matplotlib.image
    import numpy as np

    picture = io.BytesIO()
    matplotlib.image.imsave(picture, np.full((280 * rows, 4 * 280, 3), 0.8), format="png")
    return picture.getvalue()
