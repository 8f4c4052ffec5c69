"""RTDE (port 30004) of the simulated UR controller: one `RTDESession` per client connection, on asyncio.

Protocol version 2 only. Output recipes get ids 1, 2, ... per connection; input recipes get ids 1, 2, ... per
connection in the order they arrive (ur_rtde numbers its recipes itself and relies on that), or id 0 with `NOT_FOUND`
/ `IN_USE` in the type list when a name is unknown or another connection already writes it. After `S` the session
streams one `U` package per output recipe at the requested frequency until `P` or the connection ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
import time
from dataclasses import dataclass, field

from spadscan.daemon.ursim import rtde_codec as codec
from spadscan.daemon.ursim.controller import URControllerModel
from spadscan.daemon.ursim.variables import INPUT_TYPES, OUTPUT_TYPES

MAX_FREQUENCY_HZ = 500.0


@dataclass
class LinkState:
    """Link faults shared by every session: `silent` sends nothing, `frozen` repeats the package each session sends
    first after the freeze (the state at that moment), timestamp included."""

    silent: bool = False
    frozen: bool = False
    freezes: int = 0
    """Counts freezes, so that each session takes its one last package after every new one."""


@dataclass
class RTDEHub:
    """What the sessions share: the model, who writes which input, a log of requests, the link state."""

    model: URControllerModel
    version: tuple[int, int, int, int] = (5, 15, 0, 0)
    link: LinkState = field(default_factory=LinkState)
    input_owner: dict[str, int] = field(default_factory=dict)
    log: list[tuple[int, str, object]] = field(default_factory=list)
    """(session number, package letter, detail): output/input recipe names, start, pause, ..."""
    sessions: int = 0


@dataclass
class _Recipe:
    names: list[str]
    types: list[str]


class RTDESession:
    """One client connection."""

    def __init__(self, hub: RTDEHub, reader: asyncio.StreamReader, writer: asyncio.StreamWriter):
        hub.sessions += 1
        self.number = hub.sessions
        self.hub, self.reader, self.writer = hub, reader, writer
        self.outputs: dict[int, _Recipe] = {}
        self.inputs: dict[int, _Recipe] = {}
        self.frequency = 125.0
        self._stream: asyncio.Task | None = None

    async def run(self) -> None:
        """Serve until the client closes the connection or the task is cancelled."""
        buffer = bytearray()
        try:
            while data := await self.reader.read(65536):
                buffer += data
                for kind, payload in codec.split(buffer):
                    try:
                        self._handle(kind, payload)
                    except struct.error as exc:  # a package shorter than its type says: answered, not fatal
                        name = chr(kind) if 32 < kind < 127 else f"type {kind}"
                        self._note("!", f"{name}: {exc}")
                        self.writer.write(codec.text_message(f"malformed {name} package: {exc}"))
                await self.writer.drain()
        except (ConnectionError, ValueError):
            pass
        finally:
            await self._stop_stream()
            for name, owner in list(self.hub.input_owner.items()):
                if owner == self.number:
                    del self.hub.input_owner[name]
            self.writer.close()
            with contextlib.suppress(OSError, asyncio.CancelledError):
                await self.writer.wait_closed()

    def _send(self, kind: int, payload: bytes = b"") -> None:
        self.writer.write(codec.pack(kind, payload))

    def _note(self, letter: str, detail: object = None) -> None:
        self.hub.log.append((self.number, letter, detail))

    def _handle(self, kind: int, payload: bytes) -> None:
        if kind == codec.REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            self._note("V", version)
            self._send(kind, bytes([version == 2]))
        elif kind == codec.GET_URCONTROL_VERSION:
            self._note("v")
            self._send(kind, struct.pack(">IIII", *self.hub.version))
        elif kind == codec.SETUP_OUTPUTS:
            (freq,) = struct.unpack(">d", payload[:8])
            self._setup_outputs(freq, _names(payload[8:]))
        elif kind == codec.SETUP_INPUTS:
            self._setup_inputs(_names(payload))
        elif kind == codec.START:
            self._note("S")
            if self._stream is None:
                self._stream = asyncio.get_running_loop().create_task(self._stream_loop())
            self._send(kind, b"\x01")
        elif kind == codec.PAUSE:
            self._note("P")
            if self._stream is not None:
                self._stream.cancel()
                self._stream = None
            self._send(kind, b"\x01")
        elif kind == codec.DATA_PACKAGE and payload:
            recipe = self.inputs.get(payload[0])
            if recipe is not None and not self.hub.link.silent:
                values = codec.decode_values(recipe.types, payload[1:])
                self.hub.model.write_inputs(dict(zip(recipe.names, values)))
        else:
            self._note(chr(kind) if 32 < kind < 127 else "?", payload[:80])

    def _setup_outputs(self, freq: float, names: list[str]) -> None:
        self._note("O", names)
        types = [OUTPUT_TYPES.get(n, "NOT_FOUND") for n in names]
        recipe_id = 0
        if "NOT_FOUND" not in types and names:
            recipe_id = len(self.outputs) + 1
            self.outputs[recipe_id] = _Recipe(names, types)
            self.frequency = min(max(freq, 1.0), MAX_FREQUENCY_HZ) if freq > 0 else 125.0
        self._send(codec.SETUP_OUTPUTS, bytes([recipe_id]) + ",".join(types).encode())

    def _setup_inputs(self, names: list[str]) -> None:
        self._note("I", names)
        owners = self.hub.input_owner
        types = [
            "IN_USE" if owners.get(n, self.number) != self.number else INPUT_TYPES.get(n, "NOT_FOUND")
            for n in names
        ]
        recipe_id = 0
        if names and not {"NOT_FOUND", "IN_USE"} & set(types):
            recipe_id = len(self.inputs) + 1
            self.inputs[recipe_id] = _Recipe(names, types)
            owners.update({n: self.number for n in names})
        self._send(codec.SETUP_INPUTS, bytes([recipe_id]) + ",".join(types).encode())

    async def _stream_loop(self) -> None:
        period = 1.0 / self.frequency
        last: dict[int, bytes] = {}
        frozen_at = -1  # the freeze whose last package `last` holds
        next_t = time.monotonic()
        while True:
            link = self.hub.link
            if not link.silent:
                fresh = not link.frozen or frozen_at != link.freezes
                frozen_at = link.freezes if link.frozen else -1
                for rid, recipe in self.outputs.items():
                    if fresh or rid not in last:
                        values = self.hub.model.read(recipe.names)
                        last[rid] = codec.pack(codec.DATA_PACKAGE,
                                               bytes([rid]) + codec.encode_values(recipe.types, values))
                    self.writer.write(last[rid])
                await self.writer.drain()
            # An absolute schedule keeps the average rate; after a stall, skip the missed ticks.
            next_t = max(next_t + period, time.monotonic())
            await asyncio.sleep(next_t - time.monotonic())

    async def _stop_stream(self) -> None:
        if self._stream is not None:
            self._stream.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                await self._stream
            self._stream = None


def _names(payload: bytes) -> list[str]:
    """A recipe's comma-separated names; ur_rtde ends the list with a comma, which names nothing."""
    return [n.strip() for n in payload.decode(errors="replace").split(",") if n.strip()]
