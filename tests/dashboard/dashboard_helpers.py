"""Serving a captures root from a test, and asking it exactly what a browser would."""

from __future__ import annotations

import http.client
import json
import threading
from contextlib import contextmanager

from page_helpers import add_pose, start_scan
from spadscan.dashboard.server import make_server


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
