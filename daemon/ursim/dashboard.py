"""Dashboard server (port 29999) of the simulated UR controller: one text command per line, one reply line each.

ur_rtde 1.6.5's RTDEControlInterface asks, while connecting: `PolyscopeVersion`, `get serial number`,
`PolyscopeVersion` again and `is in remote control`. The other replies follow the wording of PolyScope 5 so that a
dashboard client does something sensible with them.
"""

from __future__ import annotations

import asyncio
import contextlib

from spadscan.daemon.ursim.controller import (ROBOT_MODE_NAMES, RUNTIME_PAUSED, RUNTIME_PLAYING, SAFETY_MODE_NAMES,
                                             URControllerModel)

GREETING = "Connected: Universal Robots Dashboard Server"


def reply(model: URControllerModel, line: str, version: str, serial: str) -> str:
    """The dashboard's answer to one command line."""
    cmd = line.strip()
    low = cmd.lower()
    playing = model.runtime_state == RUNTIME_PLAYING
    if low == "polyscopeversion":
        return version
    if low == "version":
        return version.split()[-1]
    if low == "get serial number":
        return serial
    if low == "get robot model":
        return "UR5"
    if low == "is in remote control":
        return "true"
    if low == "robotmode":
        return f"Robotmode: {ROBOT_MODE_NAMES[model.robot_mode]}"
    if low in ("safetymode", "safetystatus"):  # the safety mode's name: what RTDE's safety_mode reports
        return f"{cmd[0].upper()}{cmd[1:].lower()}: {SAFETY_MODE_NAMES[model.safety_mode()]}"
    if low == "running":
        return f"Program running: {'true' if playing else 'false'}"
    if low == "programstate":  # STOPPED, PLAYING or PAUSED and the program's name
        state = "PLAYING" if playing else "PAUSED" if model.runtime_state == RUNTIME_PAUSED else "STOPPED"
        return f"{state} <unnamed>"
    if low == "get loaded program":
        return "No program loaded"
    if low == "unlock protective stop":
        model.set_protective_stop(False)
        return "Protective stop releasing"
    if low == "restart safety":  # after a safety violation or fault
        model.restart_safety()
        return "Restarting safety"
    if low == "close safety popup":
        return "closing safety popup"
    if low == "close popup":
        return "closing popup"
    if low == "power on":
        model.power_on()
        return "Powering on"
    if low == "power off":
        model.power_off()
        return "Powering off"
    if low == "brake release":
        model.release_brakes()
        return "Brake releasing"
    if low == "stop":  # ends a playing or a paused program
        model.stop_program()
        return "Stopped"
    return f"could not understand: '{cmd}'"


async def serve_dashboard(model: URControllerModel, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                          log: list[str], version: str, serial: str) -> None:
    """Serve one dashboard client until it sends `quit` or closes; every command line is appended to `log`."""
    try:
        writer.write((GREETING + "\n").encode())
        while line := await reader.readline():
            text = line.decode(errors="replace").strip()
            log.append(text)
            if text.lower() == "quit":
                writer.write(b"Disconnected\n")
                break
            writer.write((reply(model, text, version, serial) + "\n").encode())
            await writer.drain()
    except ConnectionError:
        pass
    finally:
        writer.close()
        with contextlib.suppress(OSError, asyncio.CancelledError):
            await writer.wait_closed()
