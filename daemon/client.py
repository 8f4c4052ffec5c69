"""The control channel's client: one JSON line out, one JSON line back, over the daemon's Unix socket.

Standard library only (no numpy, no device code): `spadscan ctl status` must start in a blink. The wire format:
a request is `{"op": NAME, ...}\\n`; the reply is `{"ok": true, ...}\\n` or `{"ok": false, "error": "one line"}\\n`.
"""

from __future__ import annotations

import json
import os
import socket
import stat
import struct

from spadscan.protocol.errors import ConfigError, SpadscanError

MAX_REPLY_BYTES = 16 * 1024 * 1024


class ControlError(SpadscanError):
    """The daemon is unreachable, did not answer in time, or refused a request (its reason is the message)."""


class ControlTimeout(ControlError):
    """The daemon did not answer within the caller's timeout (for `wait`, the scan may simply still be running)."""


SOCKET_ROOT = "/tmp"
"""Where the default socket's private folder lives. Not $TMPDIR or $XDG_RUNTIME_DIR: a systemd service has neither
(or other values than the user's login shell), and the daemon and `spadscan ctl` must agree on the path."""


def default_socket_path(create: bool = True) -> str:
    """$SPADSCAN_SOCKET, else /tmp/spadscan-<uid>/spadscan.sock, from the uid alone: the daemon under systemd and
    `spadscan ctl` in the same user's shell find the same socket. (/run/user/<uid> exists only while the user is
    logged in: a daemon started at boot would miss it, and logging out removes it.) create: make that folder, mode
    0700, or check the one there; someone else's, or one others can write to, could hold their socket under the
    daemon's name, and is a one-line ConfigError. `spadscan ctl` only computes the path: `request` refuses a
    socket served by another user anyway."""
    env = os.environ.get("SPADSCAN_SOCKET")
    if env:
        return env
    folder = os.path.join(SOCKET_ROOT, f"spadscan-{os.getuid()}")
    if create:
        _private_folder(folder)
    return os.path.join(folder, "spadscan.sock")


def _private_folder(folder: str) -> None:
    fix = "remove it, or set SPADSCAN_SOCKET (or the config's `socket` and ctl --socket) to a path of your own"
    try:
        os.mkdir(folder, 0o700)
    except FileExistsError:
        pass
    except OSError as exc:
        raise ConfigError(f"cannot make the control socket's folder {folder}: {exc.strerror or exc}") from None
    try:
        st = os.lstat(folder)  # lstat: a symlink another user planted is not a folder of ours
    except OSError as exc:
        raise ConfigError(f"control socket folder {folder}: {exc.strerror or exc}") from None
    if not stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"control socket folder {folder} is not a folder; {fix}")
    if st.st_uid != os.getuid():
        raise ConfigError(f"control socket folder {folder} belongs to uid {st.st_uid}, not to you "
                          f"(uid {os.getuid()}); {fix}")
    if st.st_mode & 0o022:
        raise ConfigError(f"control socket folder {folder} is writable by others (mode "
                          f"{stat.S_IMODE(st.st_mode):o}); chmod 700 {folder}")


READ_ONLY_OPS = frozenset({"status", "wait"})
"""Requests that only read: one that timed out needs no word on what the daemon may still do (and the daemon
cancels one whose client hung up: `control.py`)."""


def _peer_uid(sock: socket.socket, path: str) -> int:
    """The uid of the process serving the socket: the kernel's SO_PEERCRED (struct ucred: pid, uid, gid), else the
    socket file's owner."""
    try:
        _, uid, _ = struct.unpack("iII", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                         struct.calcsize("iII")))
        return uid
    except (AttributeError, OSError):  # no SO_PEERCRED on this system
        return os.stat(path).st_uid


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
            # Scan names and options go only to a daemon of this user: anyone may bind a name in a shared folder.
            uid = _peer_uid(sock, path)
            if uid != os.getuid():
                raise ControlError(f"{path} is served by uid {uid}, not by you (uid {os.getuid()}); refusing to "
                                   f"talk to another user's process (run ctl as the daemon's user, or use another "
                                   f"socket)")
            sock.sendall((json.dumps(message) + "\n").encode())
            return _read_reply(sock, path, op)
        except socket.timeout:
            # A request sent (or partly sent) may be carried out after the caller gave up (a scan started).
            maybe = "" if op in READ_ONLY_OPS else "; it may still carry it out (check `spadscan ctl status`)"
            raise ControlTimeout(f"daemon on {path} did not answer {op!r} within {timeout_s:g} s{maybe}") from None
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
