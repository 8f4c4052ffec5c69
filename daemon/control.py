"""The control server: JSON lines over a Unix socket (mode 0600), one reply line per request line.

A request is a JSON object with an `op`; the reply is the handler's dict with `"ok": true`, or `{"ok": false,
"error": "..."}`. Bad input never stops the server: malformed JSON, non-UTF-8 or binary bytes, lines over
`max_line` bytes and unknown ops are each answered with an error and the connection keeps serving. The socket file
is created with mode 0600 (umask set around bind, then chmod), a stale one left by a crash is replaced, a live one
(another daemon) is refused, and the file is removed on close.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import stat
from pathlib import Path
from typing import AsyncIterator, Awaitable, Callable

from spadscan.protocol.errors import ConfigError, SpadscanError

log = logging.getLogger("spadscan.daemon")
MAX_LINE_BYTES = 64 * 1024

Handler = Callable[[dict], Awaitable[dict]]


def claim_socket_path(path: Path) -> None:
    """Make sure `path` is free for a new socket: remove a stale socket, refuse a live one or any other file."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(st.st_mode):
        raise ConfigError(f"socket path {path} exists and is not a socket; refusing to replace it")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.settimeout(1.0)
    try:
        probe.connect(str(path))
    except (ConnectionRefusedError, FileNotFoundError):
        os.unlink(path)  # a crashed daemon's socket: nobody listens
        return
    except OSError as exc:
        raise ConfigError(f"socket path {path}: cannot tell whether a daemon listens ({exc.strerror or exc})") from None
    finally:
        probe.close()
    raise ConfigError(f"another daemon is already listening on {path} (stop it with `spadscan ctl shutdown`)")


class ControlServer:
    """Serves `handler` on a Unix socket. Use `async with` or start()/close()."""

    def __init__(self, path, handler: Handler, *, max_line: int = MAX_LINE_BYTES):
        self.path = Path(path)
        self.handler = handler
        self.max_line = max_line
        self._server: asyncio.base_events.Server | None = None
        self._inode: tuple[int, int] | None = None
        self._clients: set[asyncio.Task] = set()

    async def start(self) -> None:
        claim_socket_path(self.path)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)  # the file is born 0600: no window in which others could connect
        try:
            sock.bind(str(self.path))
        except OSError:
            sock.close()
            raise
        finally:
            os.umask(old)
        os.chmod(self.path, 0o600)
        st = os.stat(self.path)
        self._inode = (st.st_dev, st.st_ino)
        sock.listen(16)
        sock.setblocking(False)
        self._server = await asyncio.start_unix_server(self._serve_client, sock=sock)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            for task in list(self._clients):
                task.cancel()
            if self._clients:
                await asyncio.gather(*self._clients, return_exceptions=True)
            await self._server.wait_closed()
            self._server = None
        self._remove_socket_file()

    async def __aenter__(self) -> "ControlServer":
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    def _remove_socket_file(self) -> None:
        try:
            st = os.stat(self.path)
            if (st.st_dev, st.st_ino) == self._inode:  # never remove a socket another daemon has since bound
                os.unlink(self.path)
        except FileNotFoundError:
            pass

    # ---- one connection ------------------------------------------------------------------------------------------
    async def _serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        self._clients.add(task)
        try:
            async with contextlib.aclosing(self._lines(reader)) as lines:
                async for line, problem in lines:
                    reply = {"ok": False, "error": problem} if problem else await self._answer(line)
                    writer.write((json.dumps(reply) + "\n").encode())
                    await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        except asyncio.CancelledError:
            pass  # the server is closing
        finally:
            self._clients.discard(task)
            writer.close()

    async def _lines(self, reader: asyncio.StreamReader) -> AsyncIterator[tuple[bytes, str | None]]:
        """Yield (line, None) per complete line, or (b'', problem) for a line over max_line bytes (whose rest is
        skipped up to its newline)."""
        buf = bytearray()
        skipping = False
        while True:
            data = await reader.read(65536)
            if not data:
                return
            buf += data
            while True:
                nl = buf.find(b"\n")
                if nl < 0:
                    if len(buf) > self.max_line:
                        if not skipping:
                            skipping = True
                            yield b"", f"request line longer than {self.max_line} bytes; skipped"
                        buf.clear()
                    break
                line = bytes(buf[:nl])
                del buf[: nl + 1]
                if skipping:  # the tail of an oversized line
                    skipping = False
                    continue
                if len(line) > self.max_line:
                    yield b"", f"request line longer than {self.max_line} bytes; skipped"
                    continue
                yield line, None

    async def _answer(self, line: bytes) -> dict:
        try:
            text = line.decode("utf-8")
        except UnicodeDecodeError:
            return {"ok": False, "error": "request is not UTF-8 text; send one JSON object per line"}
        if "\x00" in text:
            return {"ok": False, "error": "request contains NUL bytes; send one JSON object per line"}
        if not text.strip():
            return {"ok": False, "error": "empty request; send one JSON object per line, e.g. {\"op\": \"status\"}"}
        try:
            request = json.loads(text)
        except json.JSONDecodeError as exc:
            return {"ok": False, "error": f"malformed JSON ({exc.msg} at column {exc.colno})"}
        if not isinstance(request, dict) or not isinstance(request.get("op"), str):
            return {"ok": False, "error": "a request must be a JSON object with a string 'op'"}
        try:
            return {"ok": True, **await self.handler(request)}
        except SpadscanError as exc:
            return {"ok": False, "error": str(exc)}
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # a bug in a handler must not take the server down
            log.exception("control request %r failed", request.get("op"))
            return {"ok": False, "error": f"internal error: {type(exc).__name__}: {exc}"}
