"""RTDELink: the parent's end of one ur_rtde client process (`rtde_child.py`, whose docstring says why it exists).

`call` sends an operation and awaits its reply with a timeout; the child runs requests one at a time, in order, so
a call also waits for the ones sent before it, and its timeout counts from its turn: from when the request before
it was answered (a watchdog kick queued behind a long check of the plan's poses is not late). The link ends when a
call gets no answer in time, when ur_rtde
reports a failure (RuntimeError: a dropped link or a protocol error), or when the child dies (ur_rtde crashed): the
process is killed, every waiting call raises LinkLost saying why, and so does every later call, until the owner
starts a new link. A request whose caller gave up (cancelled) still counts: once it is past its timeout unanswered,
the next call or `stop` ends the link instead of queueing behind it. Nothing is ever left running: `stop` ends the
process (gracefully when it answers, by SIGKILL when it does not or when `stop` is cancelled) and waits for it and
for the tasks that read its pipes.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import json
import os
import signal
import time

from spadscan.daemon.devices import ArmFault, LinkLost
from spadscan.protocol.child_command import module_command
from spadscan.protocol.errors import DeviceError

_LAST_WORDS = 20  # stderr lines of the child kept for the error that reports its death


class RTDELink:
    """One ur_rtde client process; see the module docstring. Times in seconds."""

    def __init__(self, name: str):
        self.name = name
        self._proc: asyncio.subprocess.Process | None = None
        self._readers: list[asyncio.Task] = []
        # Unanswered requests, oldest first (the child answers them in order).
        self._pending: dict[int, _Request] = {}
        self._ids = 0
        self._ended: str | None = None  # why the link ended, once it has
        self._stderr: collections.deque[str] = collections.deque(maxlen=_LAST_WORDS)

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._ended is None

    async def start(self) -> None:
        """Start the child process (it connects nothing until asked to `open`)."""
        if self._proc is not None:
            raise DeviceError(f"{self.name}: the ur_rtde process was already started")
        # A session of its own: a Ctrl-C on the daemon's terminal must not end the client the daemon needs to stop
        # the arm on its way out.
        self._proc = await asyncio.create_subprocess_exec(
            *module_command("spadscan.daemon.arm.rtde_child", "--parent", os.getpid()),
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, start_new_session=True)
        self._readers = [asyncio.ensure_future(self._read_replies()), asyncio.ensure_future(self._read_stderr())]

    async def call(self, what: str, timeout_s: float, op: str, *args):
        """Run `op(*args)` in the child and return its result. LinkLost when the link has ended, when no answer comes
        within timeout_s (the link is then ended) or when ur_rtde raises RuntimeError (how it reports link and
        protocol failures); DeviceError for any other failure in the child."""
        future = asyncio.get_running_loop().create_future()
        rid = self._send(what, op, args, future, timeout_s)
        request = self._pending[rid]
        try:
            async with asyncio.timeout_at(request.deadline) as timer:
                request.timer = timer  # moved earlier when the request's turn comes
                reply = await future
        except TimeoutError:
            late = next(iter(self._pending.values()), None)
            if late is None or late is request:
                self.end(f"no answer within {timeout_s:g} s waiting for {what}; the ur_rtde process was stopped")
            else:  # its turn never came: the request ahead of it is the one stuck
                self.end(f"{late.what} got no answer in time; the ur_rtde process was stopped")
            raise LinkLost(f"{self.name}: {self._ended}") from None
        except asyncio.CancelledError:
            # The request stays pending (its reply dropped): a later call or stop sees it if it is overdue.
            request.future = request.timer = None
            if future.done() and not future.cancelled():
                future.exception()  # settled as the cancellation came: retrieved, so asyncio does not complain
            raise
        self._pending.pop(rid, None)
        if "error" not in reply:
            return reply.get("result")
        if reply["error"] == "RuntimeError":
            message = plain_rtde_error(reply["message"])
            self.end(f"{what} failed: {message}")
            raise LinkLost(f"{self.name}: {what} failed: {message}")
        if reply["error"] == "ArmNotReady":  # rtde_child.ArmNotReady: the arm runs no program; its message says why
            raise ArmFault(f"{self.name}: {reply['message']}")
        raise DeviceError(f"{self.name}: {what} failed in the ur_rtde process: {reply['error']}: {reply['message']}")

    def post(self, what: str, timeout_s: float, op: str, *args) -> None:
        """Send `op(*args)` without waiting for it (its reply is dropped): for last-ditch stops on cancellation. It runs
        after the calls sent before it, and `stop` lets it finish unless it is past timeout_s. Does nothing once the
        link has ended (never raises: its caller is already on its way out with another error)."""
        with contextlib.suppress(LinkLost):
            self._send(what, op, args, None, timeout_s)

    async def last_call(self, reason: str, timeout_s: float, what: str, op: str, *args) -> None:
        """One last request before the link is given up (a stopL, so that a move the link can no longer watch does
        not go on): wait at most timeout_s for its answer, then end the link with `reason` whatever came back. Never
        raises LinkLost."""
        future = None
        try:
            if self.alive:
                future = asyncio.get_running_loop().create_future()
                self._send(what, op, args, future, timeout_s)
                async with asyncio.timeout(timeout_s):
                    await future
        except (LinkLost, TimeoutError):
            pass
        finally:
            self.end(reason)
            if future is not None and future.done() and not future.cancelled():
                future.exception()  # retrieved: the answer no longer matters

    def end(self, reason: str) -> None:
        """End the link now (SIGKILL): waiting and later calls raise LinkLost with `reason`. Idempotent."""
        if self._ended is None:
            self._ended = reason
        if self._proc is not None and self._proc.returncode is None:
            try:
                self._proc.kill()
            except ProcessLookupError:  # exited meanwhile
                pass
        self._fail_pending()

    async def stop(self, grace_s: float) -> None:
        """End the process: close its stdin so that it finishes the requests sent so far, disconnects and exits;
        kill it after grace_s. Waits for it and for the pipe readers. Idempotent."""
        proc = self._proc
        if proc is None:
            return
        try:
            self._end_if_overdue()
            if proc.returncode is None and self._ended is None:
                try:
                    proc.stdin.close()
                    await asyncio.wait_for(proc.wait(), grace_s)
                except (TimeoutError, ConnectionError):
                    pass
        finally:  # also when cancelled: kill rather than leave the process behind
            self.end(self._ended or "the link was closed")
        await proc.wait()
        await asyncio.gather(*self._readers, return_exceptions=True)
        self._readers = []

    # -- internals ------------------------------------------------------------------------------------------------
    def _send(self, what: str, op: str, args: tuple, future: asyncio.Future | None, timeout_s: float) -> int:
        if self._proc is None:
            raise LinkLost(f"{self.name}: not connected; {what} not sent")
        self._end_if_overdue()
        if self._ended is not None:
            raise LinkLost(f"{self.name}: {self._ended}; {what} not sent, reconnect first")
        self._ids += 1
        # Its turn comes when the requests ahead of it are answered, at the latest at their deadline: until then its
        # deadline is that bound plus its own timeout, and it is moved to its turn's start plus its timeout.
        ahead = next(reversed(self._pending.values()), None)
        start = _now() if ahead is None else ahead.deadline
        self._pending[self._ids] = _Request(what, future, timeout_s, start + timeout_s, started=ahead is None)
        try:
            self._proc.stdin.write((json.dumps({"id": self._ids, "op": op, "args": list(args)}) + "\n").encode())
        except (ConnectionError, RuntimeError) as exc:  # the child is gone; its reader reports why
            self._pending.pop(self._ids, None)
            raise LinkLost(f"{self.name}: {what} not sent: the ur_rtde process is gone ({exc})") from None
        return self._ids

    def _end_if_overdue(self) -> None:
        """End the link when the request being run is still unanswered past its timeout (its caller gave up). Only
        the oldest counts: the ones behind it wait for their turn."""
        head = next(iter(self._pending.values()), None)
        if head is not None and head.started and _now() > head.deadline:
            self.end(f"{head.what} got no answer in time; the ur_rtde process was stopped")

    def _next_turn(self) -> None:
        """The oldest request left is now being run: its timeout counts from here."""
        head = next(iter(self._pending.values()), None)
        if head is not None and not head.started:
            head.started = True
            head.deadline = min(head.deadline, _now() + head.timeout_s)
            if head.timer is not None:
                head.timer.reschedule(head.deadline)

    async def _read_replies(self) -> None:
        proc = self._proc
        while line := await proc.stdout.readline():
            try:
                reply = json.loads(line)
            except ValueError:
                continue  # not a reply: nothing waits on it
            request = self._pending.pop(reply.get("id"), None)
            if request is None:
                continue
            self._next_turn()
            if request.future is not None and not request.future.done():
                request.future.set_result(reply)
        # stdout closed: the child has exited or is about to.
        returncode = await proc.wait()
        await asyncio.sleep(0)  # let the stderr reader take the last lines
        if self._ended is None:
            self._ended = f"link closed: the ur_rtde process ended ({_describe(returncode)}){self._last_words()}"
        self._fail_pending()

    async def _read_stderr(self) -> None:
        while line := await self._proc.stderr.readline():
            text = line.decode(errors="replace").strip()
            if text:
                self._stderr.append(f"{time.strftime('%H:%M:%S')} {text}")

    def _last_words(self) -> str:
        return f"; it last said: {self._stderr[-1]}" if self._stderr else ""

    def _fail_pending(self) -> None:
        pending, self._pending = self._pending, {}
        for request in pending.values():
            if request.future is not None and not request.future.done():
                request.future.set_exception(LinkLost(f"{self.name}: {self._ended}; {request.what} got no answer"))


REGISTERS_IN_USE = "One of the RTDE input registers are already in use!"
"""How ur_rtde (1.5, 1.6) starts its refusal when the controller says IN_USE for the registers of its input recipe."""


def plain_rtde_error(message: str) -> str:
    """ur_rtde's error text, with the likely cause first where its wording sends the operator astray: input
    registers in use are far more often another RTDE client on the same arm (ur_rtde names only fieldbus adapters)."""
    if REGISTERS_IN_USE.lower() in message.lower():
        return ("the arm's RTDE input registers are already in use, most likely by another RTDE client: another "
                "spadscan daemon on this arm, or a program on another computer (stop it, then start again); else by "
                "a fieldbus adapter configured on the robot (EtherNet/IP, PROFINET or MODBUS: disable it)")
    return message


@dataclasses.dataclass
class _Request:
    """One unanswered request. deadline: on the event loop's clock (s); started: its turn has come."""

    what: str
    future: asyncio.Future | None  # None: nobody waits for the reply (posted, or its caller gave up)
    timeout_s: float
    deadline: float
    started: bool
    timer: asyncio.Timeout | None = None  # the waiting call's timeout, moved when its turn comes


def _now() -> float:
    return asyncio.get_running_loop().time()


def _describe(returncode: int) -> str:
    if returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exit status {returncode}"
