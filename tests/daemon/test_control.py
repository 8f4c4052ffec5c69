"""The control socket: mode 0600, bad input answered and survived, stale sockets, the stdlib client."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import stat
import time

import pytest

from spadscan.daemon.client import ControlError, ControlTimeout, call, request
from spadscan.daemon.control import ControlServer, claim_socket_path
from spadscan.protocol.errors import ConfigError


async def echo(req: dict) -> dict:
    if req["op"] == "boom":
        raise RuntimeError("handler bug")
    if req["op"] == "refuse":
        raise ConfigError("refused for a reason")
    return {"echo": req["op"]}


async def exchange(path, payloads: list[bytes]) -> list[dict]:
    """Send raw payloads on one connection; read one reply line after each."""
    reader, writer = await asyncio.open_unix_connection(str(path), limit=1 << 22)
    replies = []
    try:
        for data in payloads:
            writer.write(data)
            await writer.drain()
            replies.append(json.loads(await asyncio.wait_for(reader.readline(), 5)))
    finally:
        writer.close()
        await writer.wait_closed()
    return replies


def test_socket_is_private_and_removed(arun, sock_dir):
    path = sock_dir / "ctl.sock"

    async def scenario():
        async with ControlServer(path, echo):
            st = os.stat(path)
            replies = await exchange(path, [b'{"op": "status"}\n'])
            return stat.S_ISSOCK(st.st_mode), stat.S_IMODE(st.st_mode), replies

    is_sock, mode, replies = arun(scenario())
    assert is_sock and mode == 0o600
    assert replies == [{"ok": True, "echo": "status"}]
    assert not path.exists()


def test_a_socket_that_cannot_be_made_is_said_with_its_path_and_key(arun, sock_dir):
    """Its folder gone (or made unwritable) after start-up checked it: the daemon said only "Operation not permitted",
    naming no path, after its devices had connected."""
    path = sock_dir / "gone" / "ctl.sock"

    async def scenario():
        async with ControlServer(path, echo):
            pass

    with pytest.raises(ConfigError) as refused:
        arun(scenario())
    assert str(refused.value) == (f"socket path {path}: cannot listen there (No such file or directory); make its "
                                  f"folder writable or choose another `socket` in the rig config")


def test_a_request_without_its_newline_is_answered_when_the_sender_closes_its_side(arun, sock_dir):
    """`printf '{"op": "status"}' | nc -U -q 5 SOCKET`: a complete request, no newline, then the sending side shut;
    the client still reads its reply."""
    path = sock_dir / "ctl.sock"

    async def scenario():
        async with ControlServer(path, echo):
            reader, writer = await asyncio.open_unix_connection(str(path))
            try:
                writer.write(b'{"op": "status"}\n{"op": "last"}')
                writer.write_eof()
                first = json.loads(await asyncio.wait_for(reader.readline(), 5))
                last = await asyncio.wait_for(reader.readline(), 5)
                tail = await asyncio.wait_for(reader.read(), 5)
            finally:
                writer.close()
                await writer.wait_closed()
            return first, last, tail

    first, last, tail = arun(scenario())
    assert first == {"ok": True, "echo": "status"}
    assert json.loads(last) == {"ok": True, "echo": "last"} and tail == b""


def test_bad_lines_get_errors_and_the_server_keeps_serving(arun, sock_dir):
    path = sock_dir / "ctl.sock"
    big = b'{"op": "' + b"x" * 200_000 + b'"}\n'

    async def scenario():
        async with ControlServer(path, echo, max_line=4096):
            one = await exchange(path, [
                b"this is not json\n",
                big,
                b"\xff\xfe\x00\x01binary\n",
                b'{"op": "st\x00atus"}\n',
                b"[1, 2, 3]\n",
                b'{"no_op": 1}\n',
                b"\n",
                b'{"op": "boom"}\n',
                b'{"op": "refuse"}\n',
                b'{"op": "status"}\n',
            ])
            # A second client is served too, also while the first one's connection is gone.
            two = await exchange(path, [b'{"op": "again"}\n'])
            return one, two

    one, two = arun(scenario())
    assert [r["ok"] for r in one] == [False] * 9 + [True]
    assert "malformed JSON" in one[0]["error"]
    assert "longer than 4096 bytes" in one[1]["error"]
    assert "UTF-8" in one[2]["error"]
    assert "NUL" in one[3]["error"]
    assert "JSON object" in one[4]["error"] and "'op'" in one[5]["error"]
    assert "empty request" in one[6]["error"]
    assert "internal error: RuntimeError: handler bug" == one[7]["error"]
    assert one[8]["error"] == "refused for a reason"
    assert one[9] == {"ok": True, "echo": "status"} and two == [{"ok": True, "echo": "again"}]


def test_oversized_line_split_across_reads(arun, sock_dir):
    """An oversized line that arrives in pieces is answered once and its tail is not taken for a request."""
    path = sock_dir / "ctl.sock"

    async def scenario():
        async with ControlServer(path, echo, max_line=1000):
            reader, writer = await asyncio.open_unix_connection(str(path))
            try:
                for _ in range(5):
                    writer.write(b"y" * 600)
                    await writer.drain()
                    await asyncio.sleep(0.01)
                writer.write(b'"}\n{"op": "after"}\n')
                await writer.drain()
                first = json.loads(await asyncio.wait_for(reader.readline(), 5))
                second = json.loads(await asyncio.wait_for(reader.readline(), 5))
            finally:
                writer.close()
                await writer.wait_closed()
            return first, second

    first, second = arun(scenario())
    assert not first["ok"] and "longer than 1000 bytes" in first["error"]
    assert second == {"ok": True, "echo": "after"}


def test_client_round_trip_and_refusal(arun, sock_dir):
    path = sock_dir / "ctl.sock"

    async def scenario():
        async with ControlServer(path, echo):
            ok = await asyncio.to_thread(call, path, "status")
            raw = await asyncio.to_thread(request, path, {"op": "refuse"})
            with pytest.raises(ControlError, match="refused for a reason"):
                await asyncio.to_thread(call, path, "refuse")
            return ok, raw

    ok, raw = arun(scenario())
    assert ok == {"ok": True, "echo": "status"}
    assert raw == {"ok": False, "error": "refused for a reason"}


def test_client_says_when_no_daemon_listens(sock_dir):
    with pytest.raises(ControlError, match="no daemon is listening on .*ctl.sock") as info:
        call(sock_dir / "ctl.sock", "status")
    assert "\n" not in str(info.value)
    # A stale socket file (nobody listening) reads the same.
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(sock_dir / "ctl.sock"))
    s.close()
    with pytest.raises(ControlError, match="no daemon is listening"):
        call(sock_dir / "ctl.sock", "status")


def test_stale_socket_is_replaced_live_one_refused(arun, sock_dir):
    path = sock_dir / "ctl.sock"
    stale = socket.socket(socket.AF_UNIX)
    stale.bind(str(path))
    stale.close()  # a crashed daemon's socket file: nobody listens

    async def scenario():
        async with ControlServer(path, echo):
            with pytest.raises(ConfigError, match="another daemon is already listening"):
                claim_socket_path(path)
            second = ControlServer(path, echo)
            with pytest.raises(ConfigError, match="another daemon"):
                await second.start()
            return await exchange(path, [b'{"op": "still"}\n'])

    assert arun(scenario()) == [{"ok": True, "echo": "still"}]
    assert not path.exists()


def test_refuses_to_replace_a_regular_file(sock_dir):
    path = sock_dir / "ctl.sock"
    path.write_text("precious")
    with pytest.raises(ConfigError, match="not a socket"):
        claim_socket_path(path)
    assert path.read_text() == "precious"


def test_close_ends_blocked_requests(arun, sock_dir):
    """A client blocked in a long request (like `wait`) is let go when the server closes."""
    path = sock_dir / "ctl.sock"
    never = None

    async def slow(req):
        await never.wait()
        return {}

    async def scenario():
        nonlocal never
        never = asyncio.Event()
        server = ControlServer(path, slow)
        await server.start()
        reader, writer = await asyncio.open_unix_connection(str(path))
        writer.write(b'{"op": "wait"}\n')
        await writer.drain()
        await asyncio.sleep(0.05)
        await server.close()
        data = await asyncio.wait_for(reader.read(), 5)
        writer.close()
        await writer.wait_closed()
        return data

    assert arun(scenario()) == b""
    assert not path.exists()


def test_a_client_that_hangs_up_on_a_pending_request_is_let_go(arun, sock_dir):
    """`wait` (reads only) is cancelled when its client hangs up; `scan` (changes things) runs to its end; a client
    that only shuts down its sending side still gets its reply. No task, no connection stays behind."""
    path = sock_dir / "ctl.sock"
    release = None
    seen: list[tuple[str, str]] = []

    async def slow(req):
        try:
            await release.wait()
        except asyncio.CancelledError:
            seen.append((req["op"], "cancelled"))
            raise
        seen.append((req["op"], "finished"))
        return {"done": req["op"]}

    async def until(pred):
        deadline = time.monotonic() + 60
        while not pred():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out; seen {seen}")
            await asyncio.sleep(0.01)

    async def scenario():
        nonlocal release
        release = asyncio.Event()
        async with ControlServer(path, slow) as server:
            for op in ("wait", "scan"):
                with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                    s.connect(str(path))
                    s.sendall(json.dumps({"op": op}).encode() + b"\n")
            # The cancelled wait's connection task ends a few loop turns after the handler saw the cancellation.
            await until(lambda: ("wait", "cancelled") in seen and len(server._clients) == 1)
            assert seen == [("wait", "cancelled")]  # scan is still running
            reader, writer = await asyncio.open_unix_connection(str(path))
            writer.write(b'{"op": "status"}\n')
            writer.write_eof()  # half-closed: it still reads
            await asyncio.sleep(3 * 0.2)
            release.set()
            reply = json.loads(await asyncio.wait_for(reader.readline(), 5))
            writer.close()
            await writer.wait_closed()
            await until(lambda: not server._clients)
            return reply

    reply = arun(scenario())
    assert reply == {"ok": True, "done": "status"}
    assert sorted(seen) == [("scan", "finished"), ("status", "finished"), ("wait", "cancelled")]


def test_json_the_parser_chokes_on_gets_an_error_and_the_connection_keeps_serving(arun, sock_dir, caplog):
    """Nesting deeper than Python's recursion limit and integers longer than its int-conversion limit raise from
    json.loads something other than JSONDecodeError; each line still gets its one-line error."""
    path = sock_dir / "ctl.sock"
    deep = b"[" * 60_000 + b"\n"
    deep_in_request = b'{"op": "status", "x": ' + b"[" * 30_000 + b"]" * 30_000 + b"}\n"
    huge_int = b'{"op": "status", "n": ' + b"7" * 5000 + b"}\n"

    async def scenario():
        async with ControlServer(path, echo):
            return await exchange(path, [deep, deep_in_request, huge_int, b'{"op": "status"}\n'])

    replies = arun(scenario())
    assert replies[:3] == [{"ok": False, "error": "malformed JSON (nested too deeply)"}] * 2 + [
        {"ok": False, "error": "malformed JSON (a number too long to read)"}]
    assert replies[3] == {"ok": True, "echo": "status"}
    assert not [r for r in caplog.records if r.levelname == "ERROR"], "no traceback in the daemon's log"


def test_an_unforeseen_parse_or_reply_failure_costs_the_line_not_the_connection(arun, sock_dir, monkeypatch):
    """The backstop: whatever parsing raises, or a reply JSON cannot hold (a handler's bug), is answered with an
    internal error and the next line on the same connection is served."""
    import spadscan.daemon.control as control

    path = sock_dir / "ctl.sock"
    real_parse = control._parse

    def parse(line):
        if b"explode" in line:
            raise MemoryError("parser gave up")
        return real_parse(line)

    async def handler(req):
        return {"value": object()} if req["op"] == "object" else await echo(req)

    monkeypatch.setattr(control, "_parse", parse)

    async def scenario():
        async with ControlServer(path, handler):
            return await exchange(path, [b'{"op": "explode"}\n', b'{"op": "object"}\n', b'{"op": "status"}\n'])

    one, two, three = arun(scenario())
    assert one == {"ok": False, "error": "internal error: MemoryError: parser gave up"}
    assert two["ok"] is False and two["error"].startswith("internal error: TypeError: Object of type object")
    assert three == {"ok": True, "echo": "status"}


def test_the_client_refuses_a_socket_served_by_another_user(arun, sock_dir, monkeypatch):
    """Another local user may bind the socket name first (a shared folder): ctl must not hand it scan names and
    options. Here the daemon is another user because this process claims another uid."""
    path = sock_dir / "ctl.sock"
    seen = []

    async def record(req):
        seen.append(req["op"])
        return {}

    real = os.getuid()

    async def scenario():
        async with ControlServer(path, record):
            with monkeypatch.context() as m, pytest.raises(ControlError) as info:
                m.setattr(os, "getuid", lambda: real + 1)
                await asyncio.to_thread(call, path, "scan", name="mug")
            return str(info.value), await asyncio.to_thread(call, path, "status")

    message, ok = arun(scenario())
    assert message == (f"{path} is served by uid {real}, not by you (uid {real + 1}); refusing to talk to another "
                       f"user's process (run ctl as the daemon's user, or use another socket)")
    assert seen == ["status"] and ok == {"ok": True}


def test_a_socket_another_user_serves_is_named_as_theirs(arun, sock_dir, monkeypatch):
    """`spadscan ctl shutdown` cannot stop another user's process: the daemon says whose socket it is instead."""
    path = sock_dir / "ctl.sock"
    real = os.getuid()

    async def scenario():
        async with ControlServer(path, echo):
            with monkeypatch.context() as m, pytest.raises(ConfigError) as info:
                m.setattr(os, "getuid", lambda: real + 1)
                claim_socket_path(path)
            return str(info.value)

    assert arun(scenario()) == (f"socket path {path} is served by another user's process (uid {real}); choose "
                                f"another socket path")


# ---- the default socket ------------------------------------------------------------------------------------------
@pytest.fixture
def socket_root(tmp_path, monkeypatch):
    """The default socket's folder made under tmp_path instead of /tmp; no SPADSCAN_SOCKET."""
    import spadscan.daemon.client as client

    monkeypatch.setattr(client, "SOCKET_ROOT", str(tmp_path))
    monkeypatch.delenv("SPADSCAN_SOCKET", raising=False)
    return tmp_path


def test_the_default_socket_depends_on_the_uid_alone(socket_root, monkeypatch):
    """A systemd service has no XDG_RUNTIME_DIR (nor the user's TMPDIR); the user's login shell has both: the
    daemon and ctl must still agree. The daemon makes the folder private; ctl only computes the path."""
    from spadscan.daemon.client import default_socket_path

    expected = str(socket_root / f"spadscan-{os.getuid()}" / "spadscan.sock")
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    monkeypatch.delenv("TMPDIR", raising=False)
    assert default_socket_path(create=False) == expected and not os.path.exists(os.path.dirname(expected))
    service = default_socket_path()
    st = os.lstat(os.path.dirname(expected))
    assert stat.S_ISDIR(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o700 and st.st_uid == os.getuid()
    (socket_root / "run-user").mkdir()
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(socket_root / "run-user"))
    monkeypatch.setenv("TMPDIR", str(socket_root / "run-user"))
    assert service == expected == default_socket_path() == default_socket_path(create=False)
    monkeypatch.setenv("SPADSCAN_SOCKET", str(socket_root / "mine.sock"))
    assert default_socket_path() == str(socket_root / "mine.sock")


@pytest.mark.parametrize("spoil, word", [
    ("other owner", "belongs to uid {real}, not to you (uid {fake})"),
    ("symlink", "is not a folder"),
    ("writable", "is writable by others (mode 777)")])
def test_a_default_socket_folder_others_could_use_is_refused(socket_root, monkeypatch, spoil, word):
    """Someone else's folder under /tmp, or one others can write to, could hold their socket under the daemon's
    name: one line saying what to do, and no socket path."""
    from spadscan.daemon.client import default_socket_path

    real = os.getuid()
    fake = real + 1 if spoil == "other owner" else real  # this process claims another uid: the folder is not its
    folder = socket_root / f"spadscan-{fake}"
    if spoil == "symlink":
        (socket_root / "elsewhere").mkdir(mode=0o700)
        folder.symlink_to(socket_root / "elsewhere")
    else:
        folder.mkdir(mode=0o700)
        if spoil == "writable":
            folder.chmod(0o777)
    with monkeypatch.context() as m, pytest.raises(ConfigError) as info:
        m.setattr(os, "getuid", lambda: fake)
        default_socket_path()
    message = str(info.value)
    assert message.startswith(f"control socket folder {folder} ") and word.format(real=real, fake=fake) in message
    assert "\n" not in message


@pytest.mark.parametrize("op, maybe", [("scan", True), ("abort", True), ("status", False), ("wait", False)])
def test_a_request_that_timed_out_says_whether_the_daemon_may_still_carry_it_out(sock_dir, op, maybe):
    """A daemon that takes the request and does not answer in time (a busy machine, a tiny --timeout): a scan it may
    still start is not a scan refused, and a retry would find it already there."""
    path = str(sock_dir / "slow.sock")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        listener.bind(path)
        listener.listen(1)  # connected from its backlog, never answered
        with pytest.raises(ControlTimeout) as info:
            request(path, {"op": op}, timeout_s=0.05)
    finally:
        listener.close()
    said = str(info.value)
    assert said.startswith(f"daemon on {path} did not answer {op!r} within 0.05 s")
    assert ("; it may still carry it out (check `spadscan ctl status`)" in said) == maybe, said


async def open_idle(path, n: int) -> list:
    """`n` connections that send nothing, each once the server has taken it (a status answered on it first)."""
    conns = []
    for _ in range(n):
        reader, writer = await asyncio.open_unix_connection(str(path))
        writer.write(b'{"op": "status"}\n')
        await writer.drain()
        assert json.loads(await asyncio.wait_for(reader.readline(), 30)) == {"ok": True, "echo": "status"}
        conns.append((reader, writer))
    return conns


async def close_all(conns) -> None:
    for _, writer in conns:
        writer.close()
        await writer.wait_closed()


def test_connections_over_the_most_served_at_once_are_told_so_and_closed(arun, sock_dir):
    """1,100 idle connections took every file a daemon under `ulimit -n 1024` may hold: its scan paused on the next
    chunk it wrote and every other client timed out. One more than the most served at once gets one error line and
    is closed; once one closes, the next is served."""
    path = sock_dir / "ctl.sock"

    async def scenario():
        async with ControlServer(path, echo, max_clients=3):
            held = await open_idle(path, 3)
            reader, writer = await asyncio.open_unix_connection(str(path))
            refused = json.loads(await asyncio.wait_for(reader.readline(), 30))
            after = await asyncio.wait_for(reader.read(), 30)
            writer.close()
            await close_all(held[:1])
            for _ in range(600):  # until the server has seen that one close: then a connection is served again
                served = await exchange(path, [b'{"op": "again"}\n'])
                if served[0]["ok"]:
                    break
                await asyncio.sleep(0.05)
            await close_all(held[1:])
            return refused, after, served

    refused, after, served = arun(scenario())
    assert refused == {"ok": False, "error": "the daemon serves 3 connections at once and all are open; close those "
                                             "left open (a script's) and try again"}
    assert after == b""
    assert served == [{"ok": True, "echo": "again"}]


def test_a_connection_idle_past_its_limit_is_closed_but_not_one_waiting_for_its_reply(arun, sock_dir):
    path = sock_dir / "ctl.sock"
    release = asyncio.Event()

    async def slow(req: dict) -> dict:
        if req["op"] == "wait":
            await release.wait()
        return {"echo": req["op"]}

    async def scenario():
        async with ControlServer(path, slow, idle_s=0.2):
            idle_reader, idle_writer = await asyncio.open_unix_connection(str(path))
            waiting_reader, waiting_writer = await asyncio.open_unix_connection(str(path))
            waiting_writer.write(b'{"op": "wait"}\n')
            await waiting_writer.drain()
            ended = await asyncio.wait_for(idle_reader.read(), 30)  # closed by the server, nothing said
            release.set()  # the pending request, far past idle_s, still gets its reply on its connection
            reply = json.loads(await asyncio.wait_for(waiting_reader.readline(), 30))
            for writer in (idle_writer, waiting_writer):
                writer.close()
                await writer.wait_closed()
            return ended, reply

    ended, reply = arun(scenario())
    assert ended == b"" and reply == {"ok": True, "echo": "wait"}
