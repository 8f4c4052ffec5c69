"""The ur_rtde client in a process of its own: `python -m spadscan.daemon.arm.rtde_child --parent PID` (started by
`RTDELink`).

Why a process: ur_rtde 1.6.5 can crash the process that holds it. When a link drops, RTDEControlInterface's receive
thread reconnects by itself; if the controller answers again while it does, that thread starts a second receive
thread and both go on reconnecting over the same socket until one reads through a freed one (SIGSEGV, seen against
the simulated controller when the link comes back within milliseconds). Here such a crash ends this process, which
the daemon reports as a lost link, and never the daemon with its open captures. A call that blocks for good (stopL
on a dead link) is ended the same way: the parent kills this process.

Requests come on stdin, one JSON line each: {"id": n, "op": name, "args": [...]}. They run one at a time, in order
(the interfaces are not thread-safe), and each gets one reply line: {"id": n, "result": ...} or
{"id": n, "error": exception class name, "message": text}. ur_rtde prints its own messages to stdout, so the
replies go to a duplicate of the original stdout and fd 1 is pointed at stderr. When stdin closes (the parent's
close, or the parent gone), the control script is stopped where it can take the command (stopScript: ur_rtde's
disconnect() leaves it running on the controller), the interfaces are disconnected and the process exits.

Its lifetime follows the parent's: it runs in a session of its own (a Ctrl-C on the daemon's terminal does not reach
it), it ignores SIGINT and SIGTERM (a service stop signals every process of the service, and the daemon still needs
the client to stop the arm on its way out), and it exits by itself when the parent is gone, even while a call
blocks.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import sys
import threading
import time

from spadscan.daemon.arm.safety_hold import holding_stop, not_ready

IK_QUERY_SINCE = {"e-Series": (5, 10), "CB-series": (3, 15)}
"""PolyScope version from which ur_rtde's control script answers getInverseKinematicsHasSolution (its lines are
marked `$5.10|3.15`; on older controllers they are left out and the answer register keeps a stale value)."""


def ik_answered(polyscope: tuple[int, int] | None) -> bool:
    """Whether a controller of PolyScope version `polyscope` (major, minor) answers the inverse-kinematics query:
    majors 5 and later by the e-Series' mark, 3 by the CB-series' (none other is known to ur_rtde's script)."""
    if polyscope is None:
        return False
    if polyscope[0] >= 5:
        return polyscope >= IK_QUERY_SINCE["e-Series"]
    return polyscope[0] == 3 and polyscope >= IK_QUERY_SINCE["CB-series"]


TCP_OFFSET_SINCE = (3, 6)
"""PolyScope version from which ur_rtde's control script answers getTCPOffset (command 40: get_tcp_offset() into
output_double_register_0..5; its lines are marked `$3.6` and left out before, when the registers keep stale values)."""


def tcp_offset_answered(polyscope: tuple[int, int] | None) -> bool:
    """Whether a controller of PolyScope version `polyscope` (major, minor) answers getTCPOffset: 3.6 on, so every
    e-Series (5.x). A controller whose dashboard names no version is asked all the same."""
    return polyscope is None or polyscope >= TCP_OFFSET_SINCE


RUNTIME_PAUSED = (3, 4)
"""RTDE runtime_state values of a program a protective or emergency stop paused: PAUSING and PAUSED (UR's client
library's RUNTIME_STATE; 1 is STOPPED, 2 PLAYING)."""
STOP_REPLY = "Stopped"
"""The dashboard server's answer to `stop` when it took it (otherwise "Failed to execute: stop")."""
PAUSED_STOP_WAIT_S = 2.0
"""How long the receive stream may take to show the program stopped after the dashboard's `stop`."""


class ArmNotReady(Exception):
    """The arm runs no program (powered off, its brakes on: `safety_hold.not_ready` says which and what to do), so
    the control script ur_rtde uploaded did not start. Not a RuntimeError: the link is fine, the arm is not."""


class CommandFailed(Exception):
    """The controller did not carry out a command (its control script is not running, or a safety stop is active).
    Not a RuntimeError: the parent ends the link on those, and this link is fine."""


class Client:
    """The two ur_rtde interfaces of one arm and the operations the parent may ask for (see `OPS`)."""

    def __init__(self):
        self.control = None
        self.receive = None
        self.polyscope: tuple[int, int] | None = None
        self.host = ""

    def open(self, host: str, frequency: float, watchdog_hz: float | None = None) -> dict:
        """Connect both interfaces (the control interface uploads its script) and, with watchdog_hz, arm the
        controller's watchdog at once (`arm_watchdog`). Returns {"polyscope": the PolyScope version [major, minor]
        the dashboard reports, or None when it says none; "watchdog": whether setWatchdog was taken}."""
        import rtde_control
        import rtde_receive

        self.host = host
        self.receive = rtde_receive.RTDEReceiveInterface(host, frequency)
        # The dashboard is asked before the script is uploaded, so that nothing stands between the upload and
        # setWatchdog (ur_rtde's advice: right after construction): a script without a watchdog runs on when this
        # process dies, and one with it only as long as the parent's kicks, which start as soon as this returns.
        self.polyscope = polyscope_version(host)
        try:
            self.control = rtde_control.RTDEControlInterface(host, frequency)
        except RuntimeError:
            # ur_rtde gives up on a script that does not start; an arm that runs no program is the operator's to
            # ready, said as such (by then its receive data has long arrived).
            unready = not_ready(int(self.receive.getRobotMode()))
            if unready is not None:
                raise ArmNotReady(unready) from None
            raise
        watchdog = watchdog_hz is not None and self.arm_watchdog(watchdog_hz)
        return {"polyscope": list(self.polyscope) if self.polyscope else None, "watchdog": watchdog}

    def arm_watchdog(self, min_frequency: float) -> bool:
        """setWatchdog, unless the script cannot take it now (not running, held by a safety stop: the parent arms it
        later); whether the controller took it."""
        if self._held() is not None:
            return False
        return self.set_watchdog(min_frequency)

    def read(self) -> dict:
        """One consistent reading: TCP pose vector [m, rad], joints [rad], controller timestamp [s], safety flags and
        status bits, whether both links are up and the control script runs, TCP speed [m/s, rad/s], the combined
        speed scaling (slider x trajectory scaling, 0..1), the pendant's speed slider alone (0..1) and UR's robot
        mode (7: running; 3: powered off; 5: its brakes on)."""
        r, c = self.receive, self.control
        if r is None or c is None:
            raise RuntimeError("interfaces are not open")
        return {"pose": list(r.getActualTCPPose()), "joints": list(r.getActualQ()), "timestamp": r.getTimestamp(),
                "protective": bool(r.isProtectiveStopped()), "emergency": bool(r.isEmergencyStopped()),
                "safety_mode": int(r.getSafetyMode()), "safety_bits": int(r.getSafetyStatusBits()),
                "connected": bool(r.isConnected() and c.isConnected()),
                "program_running": bool(c.isProgramRunning()), "tcp_speed": list(r.getActualTCPSpeed()),
                "speed_scaling": float(r.getSpeedScalingCombined()),
                "speed_slider": float(r.getTargetSpeedFraction()),
                "paused": int(r.getRuntimeState()) in RUNTIME_PAUSED, "robot_mode": int(r.getRobotMode())}

    def read_progress(self) -> dict:
        """`read`, plus whether an asynchronous move is still running and the id of the last one that started (it
        tells a new move from one a safety stop halted, whose running bit stays set)."""
        reading = self.read()
        status = self.control.getAsyncOperationProgressEx()
        reading["moving"] = bool(status.isAsyncOperationRunning())
        reading["op_id"] = int(status.operationId())
        return reading

    def move_l(self, pose: list, speed: float, accel: float) -> bool:
        """Asynchronous moveL; False when the controller refuses it."""
        return bool(self.control.moveL([float(x) for x in pose], float(speed), float(accel), True))

    def stop_l(self, decel: float) -> None:
        self.control.stopL(float(decel))

    def program_running(self) -> bool:
        return bool(self.control.isProgramRunning())

    def set_watchdog(self, min_frequency: float) -> bool:
        """The controller stops the program when no command-register input arrives for 1/min_frequency s."""
        return bool(self.control.setWatchdog(float(min_frequency)))

    def kick(self) -> bool:
        return bool(self.control.kickWatchdog())

    def reupload(self) -> bool:
        """Upload the control script again (after a fault stopped it)."""
        return bool(self.control.reuploadScript())

    def check_poses(self, poses: list) -> dict:
        """Ask the controller about each TCP pose vector in turn: isPoseWithinSafetyLimits, then (where the
        controller answers it) getInverseKinematicsHasSolution. Returns {"index": first refused or -1, "check":
        "safety" or "ik", "ik_checked": bool}. CommandFailed when the controller cannot answer (a "no" from a
        control script that is not running would read as a refusal)."""
        c = self.control
        ik = ik_answered(self.polyscope)
        for i, pose in enumerate(poses):
            pose = [float(x) for x in pose]
            if not c.isPoseWithinSafetyLimits(pose):
                self._answering("isPoseWithinSafetyLimits")
                return {"index": i, "check": "safety", "ik_checked": ik}
            if ik:
                try:
                    has = c.getInverseKinematicsHasSolution(pose)
                except RuntimeError as exc:  # ur_rtde's way of saying the command did not run
                    raise CommandFailed(f"getInverseKinematicsHasSolution: {exc}") from None
                if not has:
                    self._answering("getInverseKinematicsHasSolution")
                    return {"index": i, "check": "ik", "ik_checked": ik}
        return {"index": -1, "check": "", "ik_checked": ik}

    def tcp_offset(self) -> list[float] | None:
        """The controller's active TCP offset (getTCPOffset: a pose vector [m, rad] in the flange frame), or None
        where its PolyScope cannot tell (before 3.6). CommandFailed when the controller could not answer."""
        if not tcp_offset_answered(self.polyscope):
            return None
        try:
            offset = [float(x) for x in self.control.getTCPOffset()]
        except RuntimeError as exc:  # ur_rtde's way of saying the command did not run (a safety stop, no script)
            raise CommandFailed(f"getTCPOffset: {exc}") from None
        if len(offset) != 6:  # the command was not taken
            self._answering("getTCPOffset")
            raise CommandFailed(f"getTCPOffset: no answer ({offset})")
        return offset

    def stop_script(self) -> dict:
        """End the control script (stopScript: the program stops, and its watchdog with it), where it can take the
        command; a paused program, which takes no command, by the dashboard's `stop`. Returns {"stopped": whether no
        program runs now, "why": why it was left running or paused, else ""}."""
        # The receive stream's runtime state first: the control interface's view of the program lags it, and a
        # paused program read as "running" would be left to a stopScript it cannot take.
        if int(self.receive.getRuntimeState()) in RUNTIME_PAUSED:
            return self._stop_paused()
        if not self.control.isProgramRunning():  # true only while playing
            return {"stopped": True, "why": ""}
        why = self._held()
        if why is None:
            self.control.stopScript()  # returns once the program has stopped (or ur_rtde gave up waiting)
            if self.control.isProgramRunning():
                why = "the RTDE control script still runs after stopScript"
        return {"stopped": why is None, "why": why or ""}

    def _stop_paused(self) -> dict:
        """The dashboard's `stop` for a paused program (see `stop_script`), then until the receive stream shows it
        stopped."""
        import dashboard_client

        dashboard = dashboard_client.DashboardClient(self.host)
        try:
            dashboard.connect()
            dashboard.send("stop\n")
            answer = dashboard.receive().strip()
        except RuntimeError as exc:  # no dashboard server to ask
            return {"stopped": False, "why": f"the dashboard server did not take `stop`: {exc}"}
        finally:
            if dashboard.isConnected():
                dashboard.disconnect()
        if not answer.startswith(STOP_REPLY):
            return {"stopped": False, "why": f"the dashboard server answered `stop` with {answer!r}"}
        deadline = time.monotonic() + PAUSED_STOP_WAIT_S
        while int(self.receive.getRuntimeState()) in RUNTIME_PAUSED:
            if time.monotonic() > deadline:
                return {"stopped": False, "why": f"still paused {PAUSED_STOP_WAIT_S:g} s after the dashboard's stop"}
            time.sleep(0.02)
        return {"stopped": True, "why": ""}

    def _held(self) -> str | None:
        """Why the control script cannot take a command now (it is not running, a safety stop holds the arm), or
        None when it can. The stop is judged by `holding_stop`, as the daemon judges it from the same readings: where
        the daemon declined to send stopScript (a stop held the arm), this process declines too, also at its close."""
        c, r = self.control, self.receive
        if not c.isProgramRunning():
            return "the RTDE control script is not running"
        mode = int(r.getSafetyMode())
        stop = holding_stop(bool(r.isProtectiveStopped()), bool(r.isEmergencyStopped()), mode,
                            int(r.getSafetyStatusBits()))
        if stop is not None:
            return f"the arm is stopped for safety ({stop}, safety mode {mode})"
        return None

    def _answering(self, what: str) -> None:
        """CommandFailed unless the controller could have answered (script running, no safety stop)."""
        why = self._held()
        if why is not None:
            raise CommandFailed(f"{what}: {why}")

    def close(self) -> None:
        """Stop the control script, then disconnect both interfaces. The parent stops the script itself before an
        orderly close (and then nothing is left to stop here); this one covers a parent gone without a word."""
        if self.control is not None and self.receive is not None:
            try:
                self.stop_script()
            except RuntimeError:  # the link is dead: the controller's watchdog stops the script
                pass
        for iface in (self.control, self.receive):
            if iface is not None:
                try:
                    iface.disconnect()
                except RuntimeError:  # already dead: nothing left to close
                    pass
        self.control = self.receive = None


OPS = {"open": Client.open, "read": Client.read, "read_progress": Client.read_progress, "moveL": Client.move_l,
       "stopL": Client.stop_l, "program_running": Client.program_running, "set_watchdog": Client.set_watchdog,
       "kick": Client.kick, "reupload": Client.reupload, "check_poses": Client.check_poses,
       "tcp_offset": Client.tcp_offset, "stop_script": Client.stop_script}


def polyscope_version(host: str) -> tuple[int, int] | None:
    """The PolyScope version (major, minor) the controller's dashboard reports, or None when it names none."""
    import dashboard_client

    dashboard = dashboard_client.DashboardClient(host)
    dashboard.connect()
    try:
        m = re.search(r"(\d+)\.(\d+)", str(dashboard.polyscopeVersion()))
    finally:
        dashboard.disconnect()
    return (int(m[1]), int(m[2])) if m else None


def answer(client: Client, line: str) -> dict:
    """The reply to one request line (never raises)."""
    try:
        request = json.loads(line)
        rid, op, args = request["id"], request["op"], request.get("args", [])
    except (ValueError, KeyError, TypeError) as exc:
        return {"id": None, "error": "ValueError", "message": f"bad request {line.strip()[:80]!r}: {exc}"}
    if op not in OPS:
        return {"id": rid, "error": "ValueError", "message": f"unknown operation {op!r}"}
    try:
        return {"id": rid, "result": OPS[op](client, *args)}
    except Exception as exc:  # handed to the parent, which decides what it means
        return {"id": rid, "error": type(exc).__name__, "message": str(exc)}


def exit_with_parent(parent: int, poll_s: float = 1.0) -> None:
    """Exit at once when the parent process is gone (we were re-parented), whatever the main thread is doing."""
    while os.getppid() == parent:
        time.sleep(poll_s)
    os._exit(0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m spadscan.daemon.arm.rtde_child",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--parent", type=int, default=None,
                        help="the pid to live no longer than (default: the parent at start-up; name it, since the "
                             "parent may be gone before this process gets that far)")
    args = parser.parse_args(argv)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    threading.Thread(target=exit_with_parent, args=(args.parent or os.getppid(),), daemon=True).start()
    replies = os.fdopen(os.dup(sys.stdout.fileno()), "w", buffering=1)
    sys.stdout.flush()
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())  # ur_rtde's own printing must not mix with the replies
    client = Client()
    try:
        for line in sys.stdin:
            if line.strip():
                replies.write(json.dumps(answer(client, line)) + "\n")
    finally:
        client.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
