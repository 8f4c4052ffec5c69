"""Script port (30003) of the simulated UR controller: takes URScript programs and starts them.

ur_rtde keeps this connection open after sending its control script, so a program is recognised by its text: it
starts with `def name():` (or `sec name():`) at column 0 and is complete at the first unindented `end` line.
Each complete program (re)starts the control script in the model.
"""

from __future__ import annotations

import asyncio
import contextlib
import re

from spadscan.daemon.ursim.controller import URControllerModel

_PROGRAM_END = re.compile(rb"^end[ \t\r]*$", re.MULTILINE)
MAX_PROGRAM_BYTES = 4 * 1024 * 1024


def take_programs(buffer: bytearray) -> list[str]:
    """Remove every complete program from the front of `buffer` and return their texts."""
    programs = []
    while (m := _PROGRAM_END.search(buffer)) is not None:
        end = m.end()
        programs.append(buffer[:end].decode(errors="replace").strip())
        del buffer[: end + 1]
    return programs


async def serve_script_port(model: URControllerModel, reader: asyncio.StreamReader,
                            writer: asyncio.StreamWriter) -> None:
    """Serve one client until it closes; programs beyond MAX_PROGRAM_BYTES without an `end` are dropped."""
    buffer = bytearray()
    try:
        while data := await reader.read(65536):
            buffer += data
            for program in take_programs(buffer):
                model.start_script(program)
            if len(buffer) > MAX_PROGRAM_BYTES:
                buffer.clear()
    except ConnectionError:
        pass
    finally:
        writer.close()
        with contextlib.suppress(OSError, asyncio.CancelledError):
            await writer.wait_closed()
