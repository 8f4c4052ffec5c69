"""The dashboard's web server: the standard library's ThreadingHTTPServer, read-only, serving one captures root;
at most MAX_CONNECTIONS connections at once, each closed after IDLE_S seconds of silence.

Routes (GET and HEAD only):
  /               the page (page.html), which polls /api/status
  /api/status     the state of the root as JSON (status.py); strict JSON, a browser's parser takes it: a NaN or an
                  infinity read from a damaged file is null there
  /files/PATH     a file under the root, streamed (never read whole: chunk data, large meshes); anything that
                  resolves outside it or into a hidden folder (the queue, a job being written; through a link too)
                  and folders are 404
  /live3d/SCAN    the 3D view of SCAN's live reconstruction (recon/live/mesh.ply), made on demand and remembered
                  until the mesh changes (a few scans' only); the browser draws it (worker/report/view3d.py): the
                  server needs no OpenGL for it
"""

from __future__ import annotations

import json
import mimetypes
import os
import socket
import threading
from collections import OrderedDict
from functools import partial
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from urllib.parse import unquote, urlsplit

from spadscan.protocol.capture_format import MANIFEST
from spadscan.protocol.errors import SpadscanError
from spadscan.worker.report.report_json import json_safe

from .paths import safe_path
from .results import LIVE, RECON
from .status import Dashboard

PAGE = "page.html"
BLOCK = 1 << 16  # bytes of a served file read and sent at a time
IDLE_S = 60.0
"""Seconds a connection may keep silent (between requests, or mid-request) before it is closed."""
MAX_CONNECTIONS = 128
"""Connections served at once, each by a thread: 1,020 idle ones took every file the dashboard may hold, and every
page's polls timed out. One more gets a 503 and is closed."""


class LiveViews:
    """3D views of live meshes, made on demand and kept until the mesh file changes; the `keep` last asked for only
    (a dashboard left open for weeks sees many scans, each page a whole mesh)."""

    def __init__(self, keep: int = 4):
        self._lock = threading.Lock()
        self._keep = keep
        self._pages: OrderedDict[Path, tuple[int, bytes]] = OrderedDict()

    def page(self, mesh_path: Path, title: str) -> bytes:
        from spadscan.protocol.mesh_io import load_mesh
        from spadscan.worker.report.view3d import view3d_html

        with self._lock:
            stamp = mesh_path.stat().st_mtime_ns
            cached = self._pages.get(mesh_path)
            if cached is None or cached[0] != stamp:
                page = view3d_html(load_mesh(mesh_path, units="m"), title=title).encode("utf-8")
                self._pages[mesh_path] = cached = (stamp, page)
            self._pages.move_to_end(mesh_path)
            while len(self._pages) > self._keep:
                self._pages.popitem(last=False)
            return cached[1]

    def kept(self) -> list[Path]:
        """The meshes whose pages are kept, oldest asked for first."""
        with self._lock:
            return list(self._pages)


class Handler(BaseHTTPRequestHandler):
    """One request. `dashboard` and `live` are bound by make_server."""

    server_version = "spadscan-dashboard"
    timeout = IDLE_S  # the socket's: a silent connection is closed instead of holding its thread for good
    dashboard: Dashboard
    live: LiveViews

    def __init__(self, *args, dashboard: Dashboard, live: LiveViews, **kwargs):
        self.dashboard, self.live = dashboard, live
        super().__init__(*args, **kwargs)

    def log_message(self, format, *args):  # noqa: A002 - the standard library's name
        pass  # a poll a second would drown the terminal

    def do_HEAD(self):
        self.do_GET(head=True)

    def do_GET(self, head: bool = False):
        path = urlsplit(self.path).path
        try:
            if path in ("/", "/index.html"):
                body = resources.files("spadscan.dashboard").joinpath(PAGE).read_bytes()
                return self._send(HTTPStatus.OK, body, "text/html; charset=utf-8", head)
            if path == "/api/status":
                # json_safe: numbers come unchecked from files (json.loads takes NaN, which JSON.parse refuses:
                # one damaged meta.json or report.json would stop the page for every scan)
                body = json.dumps(json_safe(self.dashboard.status()), default=str).encode("utf-8")
                return self._send(HTTPStatus.OK, body, "application/json", head)
            if path.startswith("/files/"):
                return self._file(path[len("/files/"):], head)
            if path.startswith("/live3d/"):
                return self._live(path[len("/live3d/"):], head)
        except (BrokenPipeError, ConnectionResetError):
            return None
        except (SpadscanError, OSError) as exc:
            return self._send(HTTPStatus.SERVICE_UNAVAILABLE, f"{exc}\n".encode(), "text/plain; charset=utf-8", head)
        return self._not_found(head)

    def _file(self, rel: str, head: bool):
        path = safe_path(self.dashboard.root, rel)
        if path is None:
            return self._not_found(head)
        kind = mimetypes.guess_type(path.name)[0] or "application/octet-stream"
        if kind.startswith("text/"):
            kind += "; charset=utf-8"
        # Streamed, never read whole: /files/ serves anything under the root (chunk data, meshes of hundreds of MB).
        # Another error opening it (an unreadable disk) is said as a 503 (do_GET).
        try:
            f = path.open("rb")
        except FileNotFoundError:
            return self._not_found(head)  # removed since safe_path found it
        with f:
            size = os.fstat(f.fileno()).st_size
            self._headers(HTTPStatus.OK, size, kind)
            if not head:
                self._copy(f, size)
        return None

    def _copy(self, f, size: int):
        """`size` bytes of `f` to the client, in blocks. The headers are sent: a file cut short or unreadable from
        here closes the connection, which the client sees as a body shorter than its Content-Length (never a
        traceback, nor the rest of a file grown meanwhile beyond what was promised)."""
        left = size
        try:
            while left > 0:
                block = f.read(min(BLOCK, left))
                if not block:
                    break
                self.wfile.write(block)
                left -= len(block)
        except OSError:  # a read error, or the client gone
            pass
        if left > 0:
            self.close_connection = True

    def _live(self, scan: str, head: bool):
        mesh = safe_path(self.dashboard.root, f"{scan}/{RECON}/{LIVE}/mesh.ply")
        if mesh is None or "/" in unquote(scan).strip("/"):
            return self._not_found(head)
        try:
            body = self.live.page(mesh, title=f"{unquote(scan)} (live)")
        except FileNotFoundError:
            return self._not_found(head)  # removed since safe_path found it (a new live attempt clears it)
        return self._send(HTTPStatus.OK, body, "text/html; charset=utf-8", head)

    def _not_found(self, head: bool):
        return self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain; charset=utf-8", head)

    def _send(self, status: HTTPStatus, body: bytes, kind: str, head: bool):
        self._headers(status, len(body), kind)
        if not head:
            self.wfile.write(body)

    def _headers(self, status: HTTPStatus, length: int, kind: str):
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(length))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()


def make_server(root, host: str = "127.0.0.1", port: int = 8765, queue_dir=None,
                daemon_running=None, daemon_status=None) -> ThreadingHTTPServer:
    """A server for the captures root `root` bound to (host, port) (port 0: any free one); call serve_forever.
    `daemon_running(root)`: whether a daemon holds the root (Dashboard); None shows scans as scan.json says.
    `daemon_status(root)`: the running daemon's own status (`spadscan ctl status`'s reply), or a SpadscanError why
    it cannot be asked; None: the daemon's state is told from the scans' files alone."""
    root = check_captures_root(root)
    if not str(host).strip():
        raise SpadscanError("--host '' would listen on every interface: give 0.0.0.0 to open the page to the "
                            "network, or leave --host out for this machine only")
    if queue_dir is not None and not Path(queue_dir).is_dir():
        raise SpadscanError(f"--queue {queue_dir}: no such queue folder" +
                            (" (a file, not a folder)" if Path(queue_dir).exists() else "") +
                            " (the worker makes CAPTURES/.queue, the default)")
    handler = partial(Handler, dashboard=Dashboard(root, queue_dir, daemon_running, daemon_status=daemon_status),
                      live=LiveViews())
    try:
        server = server_class(host, port)((host, port), handler)
    except OSError as exc:
        raise SpadscanError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    server.daemon_threads = True
    return server


def check_captures_root(root) -> Path:
    """`root` as a Path when it can be a captures root: a folder that is not itself a capture, or no folder yet (the
    daemon creates it at its first scan: a dashboard started before it waits, saying so). The page of one capture
    given as the root would list no scans and a queue that does not exist, with no word of the mistake (the worker
    refuses it the same way)."""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise SpadscanError(f"{root}: no such captures root (a file, not a folder)")
    if (root / MANIFEST).is_file():
        parent = root.parent if root.name else root.resolve().parent
        raise SpadscanError(f"{root} holds {MANIFEST}: it is a capture, not a captures root (use --root {parent})")
    return root


def holds_no_scans(root) -> bool:
    """Whether the captures root lists and no sub-folder of it holds a scan manifest (hidden ones, the queue, are no
    scans), or is not there yet; False when it cannot be listed (the page says why)."""
    try:
        return not any(not p.name.startswith(".") and (p / MANIFEST).is_file() for p in Path(root).iterdir())
    except FileNotFoundError:
        return True  # the page says it waits for the root to appear
    except OSError:
        return False


class DashboardServer(ThreadingHTTPServer):
    """ThreadingHTTPServer with at most `max_connections` connections served at once (a thread each); one more is
    answered 503 and closed, so that connections left open cannot take every file and thread of the process."""

    max_connections = MAX_CONNECTIONS

    def __init__(self, *args, **kwargs):
        self._slots = threading.BoundedSemaphore(self.max_connections)
        super().__init__(*args, **kwargs)

    def process_request(self, request, client_address):
        if not self._slots.acquire(blocking=False):
            try:
                request.sendall(b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\n"
                                b"Connection: close\r\n\r\ntoo many connections open to the dashboard\n")
            except OSError:
                pass
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:  # no thread started: its slot is given back here
            self._slots.release()
            raise

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()


class IPv6Server(DashboardServer):
    """The server on an IPv6 address (ThreadingHTTPServer binds IPv4 only)."""

    address_family = socket.AF_INET6


def server_class(host: str, port: int) -> type[ThreadingHTTPServer]:
    """The server class that can bind `host`: IPv6 for a host that names IPv6 addresses only (::1, ::); IPv4
    otherwise, a name with both kinds (localhost) included. A host that does not resolve is left to the bind, whose
    error says so."""
    try:
        found = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError, OverflowError):
        return DashboardServer
    families = {info[0] for info in found}
    return IPv6Server if families == {socket.AF_INET6} else DashboardServer


def address(server: ThreadingHTTPServer) -> str:
    """The page's address, e.g. http://127.0.0.1:8765/."""
    host, port = server.server_address[:2]
    return f"http://{'[' + host + ']' if ':' in host else host}:{port}/"
