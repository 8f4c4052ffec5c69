"""The control server: JSON lines over a Unix socket (mode 0600), one reply line per request line.

A request is a JSON object with an `op`; the reply is the handler's dict with `"ok": true`, or `{"ok": false,
"error": "..."}`. Bad input never stops the server: malformed JSON, non-UTF-8 or binary bytes, lines over
`max_line` bytes and unknown ops are each answered with an error and the connection keeps serving. The socket file
is created with mode 0600 (umask set around bind, then chmod), a stale one left by a crash is replaced, a live one
(another daemon) is refused, and the file is removed on close.

A client that hangs up while its request is pending (say a `wait` on a paused scan) is noticed: while a request
runs, the server checks the connection for the peer's hang-up (POLLHUP: the peer closed its socket; a peer that only
shut down its sending side still gets its reply). A request that changes nothing of its own (`status`, `wait`; the
daemon's handler writes again, at every request, an abort a full disk kept it from recording, which a later request
tries again) is then cancelled and the connection closed; any other runs to its end, since its effect must not
depend on whether the asker still listens, and the connection closes when its reply cannot be written. Abandoned
requests hold no socket and no task.

A script that opens connections and leaves them open must not take the files the daemon writes its scan with: at
most `max_clients` connections are served at once (one more is told so in its one reply line and closed), and a
connection that sends nothing for `idle_s` seconds while no request of its is pending is closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import select
import shlex
import socket
import stat
from pathlib import Path
from typing import AsyncIterator, Awaitable, Callable

from spadscan.protocol.capture_format import fold
from spadscan.protocol.errors import ConfigError, SpadscanError

from .client import READ_ONLY_OPS, default_socket_path

log = logging.getLogger("spadscan.daemon")
MAX_LINE_BYTES = 64 * 1024
HANGUP_POLL_S = 0.2  # how often a pending request's connection is checked for the client's hang-up
MAX_CLIENTS = 128
"""Connections served at once: 1,100 idle ones took every file a daemon under `ulimit -n 1024` may hold, and its
scan paused on the next chunk it wrote."""
IDLE_S = 600.0
"""Seconds a connection may send nothing, no request of its pending, before it is closed."""
ABANDONABLE_OPS = READ_ONLY_OPS
"""Ops that only read: cancelled when the client that asked hangs up before the reply."""

Handler = Callable[[dict], Awaitable[dict]]


class SocketServed(ConfigError):
    """`check_socket_path`'s refusal of a socket that a daemon of this user listens on: `spadscan daemon --check`
    tells it apart, for the daemon may be the one of the config checked."""


def claim_socket_path(path: Path) -> None:
    """Make sure `path` is free for a new socket: remove a stale socket, refuse a live one or any other file."""
    if check_socket_path(path) == "stale":
        with contextlib.suppress(FileNotFoundError):  # a crashed daemon's socket: nobody listens
            os.unlink(path)


def check_socket_path(path: Path) -> str:
    """'free' (nothing there) or 'stale' (a socket nobody listens on); raises SocketServed for a live socket of this
    user's (another daemon), ConfigError for another user's or any other file. Changes nothing: also what `spadscan
    daemon --check` runs."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return "free"
    if not stat.S_ISSOCK(st.st_mode):
        raise ConfigError(f"socket path {path} exists and is not a socket; refusing to replace it")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.settimeout(1.0)
    try:
        probe.connect(str(path))
    except (ConnectionRefusedError, FileNotFoundError):
        return "stale"
    except OSError as exc:
        raise ConfigError(f"socket path {path}: cannot tell whether a daemon listens ({exc.strerror or exc})") from None
    finally:
        probe.close()
    if st.st_uid != os.getuid():  # not a daemon `ctl shutdown` could stop: someone may have taken the name first
        raise ConfigError(f"socket path {path} is served by another user's process (uid {st.st_uid}); choose "
                          f"another socket path")
    raise SocketServed(f"another daemon is already listening on {path} (stop it with `{shutdown_command(path)}`)")


def shutdown_command(path: Path) -> str:
    """The command that stops the daemon listening on `path`, as a shell takes it: `spadscan ctl` looks in its
    default socket (`client.default_socket_path`) unless told otherwise, so any other path goes with --socket (made
    absolute: the command may be typed in another folder)."""
    if os.path.realpath(path) == os.path.realpath(default_socket_path(create=False)):
        return "spadscan ctl shutdown"
    return f"spadscan ctl --socket {shlex.quote(os.path.abspath(path))} shutdown"


class ControlServer:
    """Serves `handler` on a Unix socket. Use `async with` or start()/close()."""

    def __init__(self, path, handler: Handler, *, max_line: int = MAX_LINE_BYTES,
                 abandonable: frozenset[str] = ABANDONABLE_OPS, max_clients: int = MAX_CLIENTS,
                 idle_s: float = IDLE_S):
        self.path = Path(path)
        self.handler = handler
        self.max_line = max_line
        self.max_clients = max_clients
        self.idle_s = idle_s
        self._turning_away = False
        self.abandonable = frozenset(abandonable)
        self._server: asyncio.base_events.Server | None = None
        self._inode: tuple[int, int] | None = None
        self._clients: set[asyncio.Task] = set()

    async def start(self) -> None:
        claim_socket_path(self.path)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)  # the file is born 0600: no window in which others could connect
        try:
            sock.bind(str(self.path))
        except OSError as exc:  # the folder changed since start-up checked it: said with the path and the key
            sock.close()
            raise ConfigError(f"socket path {self.path}: cannot listen there ({exc.strerror or exc}); make its "
                              f"folder writable or choose another `socket` in the rig config") from None
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
        if len(self._clients) >= self.max_clients:
            await self._turn_away(writer)
            return
        self._turning_away = False
        task = asyncio.current_task()
        self._clients.add(task)
        sock = writer.get_extra_info("socket")
        try:
            async with contextlib.aclosing(self._lines(reader)) as lines:
                async for line, problem in lines:
                    if problem:
                        reply = {"ok": False, "error": problem}
                    else:
                        reply = await self._answer_while_connected(line, sock)
                    writer.write(_encode(reply))
                    await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        except asyncio.CancelledError:
            pass  # the server is closing, or the client hung up on a read-only request
        finally:
            self._clients.discard(task)
            writer.close()

    async def _turn_away(self, writer: asyncio.StreamWriter) -> None:
        """One connection more than `max_clients`: told so in one reply line, and closed. Logged once a run of them
        (until a connection is served again)."""
        if not self._turning_away:
            log.warning("control socket: %d connections open, the most served at once; turning new ones away "
                        "until some close", len(self._clients))
        self._turning_away = True
        error = (f"the daemon serves {self.max_clients} connections at once and all are open; close those left "
                 f"open (a script's) and try again")
        with contextlib.suppress(ConnectionError):
            writer.write(_encode({"ok": False, "error": error}))
            await writer.drain()
        writer.close()

    async def _answer_while_connected(self, line: bytes, sock) -> dict:
        """The reply to one line. The handler runs in this task, so its reply is written before anything it
        scheduled (shutdown's stop) runs. A read-only request is watched: when its client hangs up, this task is
        cancelled, which ends the request and the connection (see the module docstring)."""
        try:
            request, reply = _parse(line)
        except Exception as exc:  # a parsing case _parse does not know must cost this line, not the connection
            log.exception("control request line could not be parsed")
            return _internal_error(exc)
        if request is None:
            return reply
        if request["op"] not in self.abandonable:
            return await self._answer(request)  # a client that hung up meanwhile: the reply's write fails
        watcher = asyncio.create_task(self._watch_hangup(sock, request["op"], asyncio.current_task()))
        try:
            return await self._answer(request)
        finally:
            watcher.cancel()
            await asyncio.gather(watcher, return_exceptions=True)

    @staticmethod
    async def _watch_hangup(sock, op: str, serving: asyncio.Task) -> None:
        while not _peer_gone(sock):
            await asyncio.sleep(HANGUP_POLL_S)
        log.info("control client hung up while %r was pending; cancelled", op)
        serving.cancel()

    async def _lines(self, reader: asyncio.StreamReader) -> AsyncIterator[tuple[bytes, str | None]]:
        """Yield (line, None) per complete line, or (b'', problem) for a line over max_line bytes (whose rest is
        skipped up to its newline). Text after the last newline counts as a line when the client closes its
        sending side (it may still read the reply). Ends when the client sends nothing for idle_s seconds."""
        buf = bytearray()
        skipping = False
        while True:
            try:
                data = await asyncio.wait_for(reader.read(65536), self.idle_s)
            except asyncio.TimeoutError:  # nothing asked for idle_s: the connection is closed
                return
            if not data:
                # The client shut its sending side after a complete request without the newline: still a request.
                if buf.strip() and not skipping and len(buf) <= self.max_line:
                    yield bytes(buf), None
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

    async def _answer(self, request: dict) -> dict:
        try:
            return {"ok": True, **await self.handler(request)}
        except SpadscanError as exc:
            return {"ok": False, "error": str(exc)}
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # a bug in a handler must not take the server down
            log.exception("control request %r failed", request.get("op"))
            return _internal_error(exc)


def _internal_error(exc: Exception) -> dict:
    return {"ok": False, "error": f"internal error: {type(exc).__name__}: {fold(exc)}"}


def _encode(reply: dict) -> bytes:
    """One reply line. A reply JSON cannot hold (a handler's bug: an object, a nested loop) becomes an error reply,
    so that the client still gets its line and the connection keeps serving."""
    try:
        return (json.dumps(reply) + "\n").encode()
    except (TypeError, ValueError, RecursionError) as exc:
        log.exception("control reply could not be encoded")
        return (json.dumps(_internal_error(exc)) + "\n").encode()


def _parse(line: bytes) -> tuple[dict | None, dict | None]:
    """(request, None) for a well-formed request line, else (None, error reply)."""
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError:
        return None, {"ok": False, "error": "request is not UTF-8 text; send one JSON object per line"}
    if "\x00" in text:
        return None, {"ok": False, "error": "request contains NUL bytes; send one JSON object per line"}
    if not text.strip():
        return None, {"ok": False, "error": "empty request; send one JSON object per line, e.g. {\"op\": \"status\"}"}
    try:
        request = json.loads(text)
    except json.JSONDecodeError as exc:
        return None, {"ok": False, "error": f"malformed JSON ({exc.msg} at column {exc.colno})"}
    except RecursionError:  # arrays nested thousands deep, well inside max_line
        return None, {"ok": False, "error": "malformed JSON (nested too deeply)"}
    except ValueError:  # an integer of more digits than Python converts (sys.get_int_max_str_digits)
        return None, {"ok": False, "error": "malformed JSON (a number too long to read)"}
    if not isinstance(request, dict) or not isinstance(request.get("op"), str):
        return None, {"ok": False, "error": "a request must be a JSON object with a string 'op'"}
    return request, None


def _peer_gone(sock) -> bool:
    """True when the client closed its socket (POLLHUP on a Unix stream socket: both directions shut down; a
    client that only shut down its sending side still reads). Checked without reading: the data stays queued."""
    if sock is None:
        return False
    try:
        poller = select.poll()
        poller.register(sock.fileno(), select.POLLHUP)
        return any(ev & (select.POLLHUP | select.POLLERR | select.POLLNVAL) for _, ev in poller.poll(0))
    except (OSError, ValueError):
        return True
