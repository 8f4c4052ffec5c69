"""A stand-in daemon on a Unix socket that answers `status` with a given reply and refuses every other operation:
enough for `spadscan ctl status` run as a real process, against the daemon's line protocol."""

from __future__ import annotations

import json
import socketserver


class StatusDaemon(socketserver.ThreadingUnixStreamServer):
    daemon_threads = True

    def __init__(self, path: str, status: dict):
        self.reply = status
        super().__init__(path, _Handler)


class _Handler(socketserver.StreamRequestHandler):
    def handle(self) -> None:
        req = json.loads(self.rfile.readline())
        reply = {"ok": True, **self.server.reply} if req["op"] == "status" else {"ok": False, "error": "no"}
        self.wfile.write((json.dumps(reply) + "\n").encode())
