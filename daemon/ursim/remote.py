"""The simulated UR controller in a child process, driven over its stdin/stdout by JSON lines.

ur_rtde's constructors hold the Python GIL while they wait for the controller, so a controller served by a thread of
the same process never answers them: a process that uses the real client runs the controller as a child.
`SimURProcess` starts `python -m spadscan.daemon.ursim --host H --control-stdio` and offers the same fault API and
records as `SimURController`; each request is one line `{"op": ..., "args": {...}}`, each reply one line
`{"ok": true, "result": ...}` or `{"ok": false, "error": "..."}`.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import asdict

from spadscan.daemon.ursim.controller import MoveRecord
from spadscan.daemon.ursim.sim_controller import SimURController
from spadscan.protocol.child_command import module_command
from spadscan.protocol.errors import DeviceError, SpadscanError

_CALLS = ("protective_stop", "clear_protective_stop", "safeguard_stop", "clear_safeguard_stop", "emergency_stop",
          "clear_emergency_stop", "safety_fault", "restart_safety", "power_on", "release_brakes", "drop_link",
          "restore_link", "configure")


def handle(controller: SimURController, request: dict) -> object:
    """Carry out one request on a running controller; returns a JSON-able result."""
    op, args = request.get("op"), request.get("args") or {}
    if op in _CALLS:
        return getattr(controller, op)(**args)
    if op == "moves":
        return [asdict(m) for m in controller.moves]
    if op == "pose":
        return controller.model.read(["actual_TCP_pose"])[0]
    if op == "set_pose":
        return controller.model.set_pose(args["pose"])
    if op == "scripts":
        return len(controller.scripts)
    if op == "state":
        m = controller.model
        return {"runtime_state": m.runtime_state, "watchdog_period_s": m.watchdog_period_s,
                "watchdog_stops": m.watchdog_stops, "script_stops": m.script_stops,
                "dashboard_stops": m.dashboard_stops, "errors": list(m.errors),
                "queries": [list(q) for q in m.queries], "tcp_offset_reads": m.tcp_offset_reads,
                "safety_mode": m.read(["safety_mode"])[0],
                "moving": m.read(["output_int_register_2"])[0] & 32768 != 0,
                "script_state": m.read(["output_int_register_0"])[0]}
    if op == "dashboard_log":
        return controller.dashboard_log
    if op == "rtde_log":
        return [[s, k, d if isinstance(d, (int, list, type(None))) else repr(d)] for s, k, d in controller.rtde_log]
    if op == "open_connections":
        return controller.open_connections()
    if op == "connections":
        return controller.connections
    raise DeviceError(f"unknown request {op!r}")


def serve_stdio(controller: SimURController, stdin=sys.stdin, stdout=sys.stdout) -> None:
    """Answer requests from stdin until it closes or says {"op": "quit"}; the controller must be started."""
    for line in stdin:
        if not line.strip():
            continue
        try:
            request = json.loads(line)
            if request.get("op") == "quit":
                break
            reply = {"ok": True, "result": handle(controller, request)}
        except (SpadscanError, ValueError, KeyError, TypeError) as exc:
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        stdout.write(json.dumps(reply) + "\n")
        stdout.flush()


class SimURProcess:
    """A simulated UR controller in a child process (see the module docstring). Use as a context manager."""

    def __init__(self, host: str, *, time_scale: float = 1.0, start_timeout_s: float = 30.0):
        self.host = host
        self._proc = subprocess.Popen(
            module_command("spadscan.daemon.ursim", "--host", host, "--time-scale", time_scale, "--control-stdio"),
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1,
        )
        line = self._proc.stdout.readline()
        if not line.startswith("ursim listening"):
            err = self._finish(start_timeout_s)
            raise DeviceError(f"simulated UR controller on {host} did not start: {err or line.strip()}")

    def _request(self, op: str, **args) -> object:
        if self._proc.poll() is not None:
            raise DeviceError(f"simulated UR controller on {self.host} has exited ({self._proc.returncode})")
        self._proc.stdin.write(json.dumps({"op": op, "args": args}) + "\n")
        self._proc.stdin.flush()
        reply = json.loads(self._proc.stdout.readline() or '{"ok": false, "error": "no reply"}')
        if not reply["ok"]:
            raise DeviceError(f"simulated UR controller on {self.host}: {op}: {reply['error']}")
        return reply["result"]

    def protective_stop(self) -> None:
        self._request("protective_stop")

    def clear_protective_stop(self) -> None:
        self._request("clear_protective_stop")

    def safeguard_stop(self) -> None:
        self._request("safeguard_stop")

    def clear_safeguard_stop(self) -> None:
        self._request("clear_safeguard_stop")

    def configure(self, **settings) -> None:
        """See SimURController.configure."""
        self._request("configure", **settings)

    def state(self) -> dict:
        """runtime_state (1 stopped, 2 playing, 4 paused), watchdog_period_s, watchdog_stops, script_stops (programs
        ended by their stop command, ur_rtde's stopScript), dashboard_stops (programs, playing or paused, ended by the
        dashboard's `stop`), errors, queries (name, pose, answer), tcp_offset_reads
        (get_tcp_offset commands answered), safety_mode (RTDE's), whether an asynchronous move is running,
        script_state (1 ready for a command, 2 done with one)."""
        return self._request("state")

    def emergency_stop(self) -> None:
        self._request("emergency_stop")

    def clear_emergency_stop(self) -> None:
        self._request("clear_emergency_stop")

    def safety_fault(self, kind: str = "fault") -> None:
        """See SimURController.safety_fault: "violation" or "fault"."""
        self._request("safety_fault", kind=kind)

    def restart_safety(self) -> None:
        self._request("restart_safety")

    def power_on(self) -> None:
        self._request("power_on")

    def release_brakes(self) -> None:
        self._request("release_brakes")

    def drop_link(self, mode: str = "silent") -> None:
        """See SimURController.drop_link: "close", "silent" or "freeze"."""
        self._request("drop_link", mode=mode)

    def restore_link(self) -> None:
        self._request("restore_link")

    def set_pose(self, pose_vec) -> None:
        self._request("set_pose", pose=[float(x) for x in pose_vec])

    @property
    def moves(self) -> list[MoveRecord]:
        return [MoveRecord(**{**m, "target": tuple(m["target"])}) for m in self._request("moves")]

    def pose(self) -> list[float]:
        """The controller's actual TCP pose vector (6,) now."""
        return self._request("pose")

    def scripts(self) -> int:
        """How many programs arrived on the script port."""
        return self._request("scripts")

    def dashboard_log(self) -> list[str]:
        return self._request("dashboard_log")

    def rtde_log(self) -> list:
        return self._request("rtde_log")

    def open_connections(self) -> int:
        return self._request("open_connections")

    def connections(self) -> dict[str, int]:
        return self._request("connections")

    def _finish(self, timeout_s: float) -> str:
        """Close stdin (the child stops and joins its servers), wait, kill if needed; returns its stderr."""
        try:
            self._proc.stdin.close()
        except OSError:
            pass
        try:
            self._proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        err = self._proc.stderr.read()
        self._proc.stdout.close()
        self._proc.stderr.close()
        return err.strip()

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop the child process. Idempotent."""
        if self._proc.stdin.closed:
            return
        self._finish(timeout_s)

    def __enter__(self) -> SimURProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
