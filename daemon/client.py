"""The control channel's client: one JSON line out, one JSON line back, over the daemon's Unix socket.

Standard library only (no numpy, no device code): `spadscan ctl status` must start in a blink. The wire format:
a request is `{"op": NAME, ...}\\n`; the reply is `{"ok": true, ...}\\n` or `{"ok": false, "error": "one line"}\\n`.
"""

from __future__ import annotations

import json
import os
import socket

from spadscan.protocol.errors import SpadscanError

MAX_REPLY_BYTES = 16 * 1024 * 1024


class ControlError(SpadscanError):
    """The daemon is unreachable, did not answer in time, or refused a request (its reason is the message)."""


class ControlTimeout(ControlError):
    """The daemon did not answer within the caller's timeout (for `wait`, the scan may simply still be running)."""


def default_socket_path() -> str:
    """$SPADSCAN_SOCKET, else $XDG_RUNTIME_DIR/spadscan.sock, else /tmp/spadscan-<uid>.sock."""
    env = os.environ.get("SPADSCAN_SOCKET")
    if env:
        return env
    run = os.environ.get("XDG_RUNTIME_DIR")
    if run and os.path.isdir(run):
        return os.path.join(run, "spadscan.sock")
    return f"/tmp/spadscan-{os.getuid()}.sock"


def request(socket_path, message: dict, timeout_s: float | None = 10.0) -> dict:
    """Send one request and return the daemon's reply (a dict with 'ok'). timeout_s None waits forever."""
    path = str(socket_path)
    op = message.get("op", "?")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.settimeout(timeout_s)
        try:
            sock.connect(path)
        except (FileNotFoundError, ConnectionRefusedError):
            raise ControlError(f"no daemon is listening on {path} (start one with "
                               f"`spadscan daemon --config rig.toml`, or pass --socket)") from None
        except PermissionError:
            raise ControlError(f"{path}: permission denied (the daemon runs as another user?)") from None
        except OSError as exc:
            raise ControlError(f"cannot connect to {path}: {exc.strerror or exc}") from None
        try:
            sock.sendall((json.dumps(message) + "\n").encode())
            return _read_reply(sock, path, op)
        except socket.timeout:
            raise ControlTimeout(f"daemon on {path} did not answer {op!r} within {timeout_s:g} s") from None
        except OSError as exc:
            raise ControlError(f"lost the connection to the daemon on {path} during {op!r}: "
                               f"{exc.strerror or exc}") from None
    finally:
        sock.close()


def _read_reply(sock: socket.socket, path: str, op: str) -> dict:
    buf = bytearray()
    while b"\n" not in buf:
        data = sock.recv(65536)
        if not data:
            raise ControlError(f"the daemon on {path} closed the connection during {op!r} (did it stop?)")
        buf += data
        if len(buf) > MAX_REPLY_BYTES:
            raise ControlError(f"the daemon on {path} sent a reply over {MAX_REPLY_BYTES} bytes")
    line = bytes(buf[: buf.index(b"\n")])
    try:
        reply = json.loads(line)
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise ControlError(f"the daemon on {path} sent a malformed reply to {op!r}") from None
    if not isinstance(reply, dict) or "ok" not in reply:
        raise ControlError(f"the daemon on {path} sent a reply without 'ok' to {op!r}")
    return reply


def call(socket_path, op: str, timeout_s: float | None = 10.0, **args) -> dict:
    """Send a request; return the reply, or raise ControlError with the daemon's reason when it refused."""
    reply = request(socket_path, {"op": op, **args}, timeout_s)
    if not reply["ok"]:
        raise ControlError(str(reply.get("error", "request refused")))
    return reply
