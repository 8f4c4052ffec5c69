"""SimURController: the simulated UR controller's three servers on one loopback address, and its fault API.

    with SimURController("127.0.0.9", time_scale=0.01) as ur:
        ... RTDEControlInterface("127.0.0.9") ...
        ur.protective_stop(); ur.clear_protective_stop()     # also safeguard_stop, emergency_stop
        ur.safety_fault("fault"); ur.restart_safety()         # or "violation": cleared only by a restart
        ur.drop_link("silent"); ur.restore_link()
        ur.configure(speed_slider=0.5, pose_noise_m=2e-4, safety_floor_z=0.05, tcp_offset=(0, 0, 0.1, 0, 0, 0))
        ur.moves  # every command the controller took

The servers run on an asyncio loop in one background thread (`start`/`stop`, or a `with` block), or in the caller's
loop (`await serve()`, as `python -m spadscan.daemon.ursim` does). Ports are the controller's fixed ones (ur_rtde
does not let a client choose), so concurrent controllers need distinct addresses 127.0.0.N.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import threading
from collections.abc import Callable

from spadscan.daemon.ursim.controller import SAFETY_FAULT, SAFETY_VIOLATION, MoveRecord, URControllerModel
from spadscan.daemon.ursim.dashboard import serve_dashboard
from spadscan.daemon.ursim.rtde_server import RTDEHub, RTDESession
from spadscan.daemon.ursim.script_port import serve_script_port
from spadscan.protocol.errors import DeviceError

LINK_MODES = ("close", "silent", "freeze")
WATCHDOG_POLL_S = 0.005
"""How often the RTDE watchdog is checked (the real controller checks every control cycle, 2 ms)."""
SETTINGS = ("speed_slider", "pose_noise_m", "safety_floor_z", "reach_m", "move_thread_start_s", "tcp_offset")
"""What `configure` may change while the controller runs."""


class SimURController:
    """A UR controller on loopback that ur_rtde 1.6.5 accepts; see the module docstring."""

    def __init__(self, host: str = "127.0.0.1", *, time_scale: float = 1.0, rtde_port: int = 30004,
                 dashboard_port: int = 29999, script_port: int = 30003, version: tuple = (5, 15, 0, 0),
                 polyscope: str = "URSoftware 5.15.0.0 (Dec 01 2023)", serial: str = "20205500001",
                 initial_pose=(0.3, 0.0, 0.3, 0.0, math.pi, 0.0)):
        if not math.isfinite(time_scale) or time_scale < 0:
            raise DeviceError(f"time_scale must be finite and >= 0, got {time_scale}")
        self.host = host
        self.ports = {"rtde": rtde_port, "dashboard": dashboard_port, "script": script_port}
        self.model = URControllerModel(time_scale=time_scale, initial_pose=initial_pose)
        self.hub = RTDEHub(self.model, tuple(version))
        self.polyscope, self.serial = polyscope, serial
        self.dashboard_log: list[str] = []
        self.connections = {name: 0 for name in self.ports}
        """Connections accepted so far, per server."""
        self._servers: list[asyncio.AbstractServer] = []
        self._tasks: set[asyncio.Task] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_event: asyncio.Event | None = None
        self._thread: threading.Thread | None = None

    # -- running ---------------------------------------------------------------------------------------------
    async def serve(self, ready: Callable[[], None] | None = None) -> None:
        """Listen and serve in the running loop until `request_stop()`; then close every connection."""
        self._loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        await self._listen()
        watchdog = self._loop.create_task(self._watch_inputs())
        try:
            if ready is not None:
                ready()
            await self._stop_event.wait()
        finally:
            watchdog.cancel()
            await asyncio.gather(watchdog, return_exceptions=True)
            await self._disconnect_all()

    async def _watch_inputs(self) -> None:
        """The RTDE watchdog, independent of any connection (a client that died has none)."""
        while True:
            await asyncio.sleep(WATCHDOG_POLL_S)
            if self.model.watchdog_due():
                for _ in range(3):  # input already waiting on a socket is read first (see watchdog_due)
                    await asyncio.sleep(0)
                self.model.check_watchdog()

    def request_stop(self) -> None:
        """Ask `serve()` to finish (thread-safe)."""
        loop, event = self._loop, self._stop_event
        if loop is not None and event is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(event.set)
            except RuntimeError:  # the loop closed meanwhile: nothing left to stop
                pass

    def start(self, timeout_s: float = 10.0) -> SimURController:
        """Serve from a background thread; returns once listening. Raises DeviceError when it cannot listen."""
        if self._thread is not None:
            return self
        ready = threading.Event()
        errors: list[BaseException] = []

        def target() -> None:
            try:
                asyncio.run(self.serve(ready.set))
            except BaseException as exc:  # reported to start()'s caller below
                errors.append(exc)
                ready.set()

        self._thread = threading.Thread(target=target, name=f"ursim-{self.host}", daemon=True)
        self._thread.start()
        if not ready.wait(timeout_s) or errors:
            self.stop()
            why = f"{errors[0]}" if errors else f"not listening after {timeout_s} s"
            raise DeviceError(f"simulated UR controller on {self.host}: {why}")
        return self

    def stop(self, timeout_s: float = 10.0) -> None:
        """Close every server and connection and join the thread. Idempotent."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self.request_stop()
        thread.join(timeout_s)
        if thread.is_alive():
            raise DeviceError(f"simulated UR controller on {self.host} did not stop within {timeout_s} s")

    def __enter__(self) -> SimURController:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- faults (thread-safe) --------------------------------------------------------------------------------
    def protective_stop(self) -> None:
        """Safety mode 3, safety_status_bits bit 2; motion halts and the program pauses (runtime_state 4): it takes no
        command, also once the stop is cleared, until the script is uploaded again."""
        self.model.set_protective_stop(True)

    def clear_protective_stop(self) -> None:
        self.model.set_protective_stop(False)

    def safeguard_stop(self) -> None:
        """Safeguard stop (safety mode 5, safety_status_bits bit 4); motion halts until it is cleared."""
        self.model.set_safeguard_stop(True)

    def clear_safeguard_stop(self) -> None:
        self.model.set_safeguard_stop(False)

    def emergency_stop(self) -> None:
        """Robot emergency stop (safety mode 7, safety_status_bits bits 6 and 7); the program pauses, as on a protective
        stop."""
        self.model.set_emergency_stop(True)

    def clear_emergency_stop(self) -> None:
        self.model.set_emergency_stop(False)

    def safety_fault(self, kind: str = "fault") -> None:
        """The safety system stops the arm and the program: "violation" (safety mode 8, safety_status_bits bit 8) or
        "fault" (safety mode 9, bit 9); only `restart_safety` clears it."""
        modes = {"violation": SAFETY_VIOLATION, "fault": SAFETY_FAULT}
        if kind not in modes:
            raise DeviceError(f"safety fault kind must be one of {sorted(modes)}, got {kind!r}")
        self.model.set_safety_fault(modes[kind])

    def restart_safety(self) -> None:
        """Restart the arm as from the pendant after a violation or fault: it comes back powered off (robot mode 3);
        `power_on` and `release_brakes` ready it, and the script must be uploaded again."""
        self.model.restart_safety()

    def power_on(self) -> None:
        """Power the arm on as from the pendant (or the dashboard's `power on`): its brakes stay on (robot mode 5)."""
        self.model.power_on()

    def release_brakes(self) -> None:
        """Release the brakes of a powered arm (the dashboard's `brake release`): ready to run a program (mode 7)."""
        self.model.release_brakes()

    def configure(self, **settings) -> None:
        """Change what makes the controller less than ideal (thread-safe): speed_slider (0 < f <= 1), pose_noise_m
        (m), safety_floor_z (m or None), reach_m (m), move_thread_start_s (s: how long an asynchronous move takes to
        report itself running; one controller cycle by default), tcp_offset (the pendant's active TCP offset, a pose
        vector [m, rad] in the flange frame, which get_tcp_offset answers; zero, the bare flange, by default)."""
        unknown = set(settings) - set(SETTINGS)
        if unknown:
            raise DeviceError(f"unknown controller settings {sorted(unknown)} (known: {', '.join(SETTINGS)})")
        if "speed_slider" in settings:
            try:
                self.model.set_speed_slider(float(settings.pop("speed_slider")))
            except ValueError as exc:
                raise DeviceError(str(exc)) from None
        if "tcp_offset" in settings:
            offset = settings["tcp_offset"]
            try:
                offset = tuple(float(x) for x in offset)
            except (TypeError, ValueError):
                offset = ()
            if len(offset) != 6 or not all(map(math.isfinite, offset)):
                raise DeviceError(f"tcp_offset must be six finite numbers [m, rad], got {settings['tcp_offset']!r}")
            settings["tcp_offset"] = offset
        for name in ("pose_noise_m", "reach_m", "move_thread_start_s"):
            value = settings.get(name, 0.0)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise DeviceError(f"{name} must be a finite number >= 0, got {value!r}")
        for name, value in settings.items():
            setattr(self.model, name, value)

    def drop_link(self, mode: str = "silent") -> None:
        """Break the link. "close": close every connection and refuse new ones; "silent": connections stay open
        but nothing flows either way and new ones are refused (a pulled cable); "freeze": data keeps coming but
        repeats the last package, timestamp included (a hung controller)."""
        if mode not in LINK_MODES:
            raise DeviceError(f"link drop mode must be one of {LINK_MODES}, got {mode!r}")
        if mode == "freeze":
            self.hub.link.freezes += 1
            self.hub.link.frozen = True
            return
        self.hub.link.silent = mode == "silent"
        self._call(self._unlisten())
        if mode == "close":
            self._call(self._disconnect_all())

    def restore_link(self) -> None:
        """Undo drop_link: listen again, let data flow."""
        self.hub.link.silent = self.hub.link.frozen = False
        if not self._servers:
            self._call(self._listen())

    def _call(self, coro) -> None:
        if self._loop is None:
            coro.close()
            raise DeviceError(f"simulated UR controller on {self.host} is not running")
        if self._thread is not None and threading.current_thread() is not self._thread:
            asyncio.run_coroutine_threadsafe(coro, self._loop).result(10.0)
        else:
            self._loop.create_task(coro)

    # -- inspection ------------------------------------------------------------------------------------------
    @property
    def moves(self) -> list[MoveRecord]:
        """Every command the controller took (moves and stops), oldest first."""
        return list(self.model.moves)

    @property
    def scripts(self) -> list[str]:
        """Every program received on the script port."""
        return list(self.model.scripts)

    @property
    def rtde_log(self) -> list[tuple[int, str, object]]:
        """(session, package letter, detail) for every RTDE request other than data packages."""
        return list(self.hub.log)

    def open_connections(self) -> int:
        """Client connections currently open (any server)."""
        return sum(1 for t in list(self._tasks) if not t.done())

    # -- servers -----------------------------------------------------------------------------------------------
    async def _listen(self) -> None:
        handlers = {"rtde": self._serve_rtde, "dashboard": self._serve_dashboard, "script": self._serve_script}
        try:
            for name, port in self.ports.items():
                self._servers.append(await asyncio.start_server(handlers[name], self.host, port))
        except OSError:
            await self._unlisten()
            raise

    async def _unlisten(self) -> None:
        servers, self._servers = self._servers, []
        for server in servers:
            server.close()
        for server in servers:
            await server.wait_closed()

    async def _disconnect_all(self) -> None:
        await self._unlisten()
        tasks = [t for t in self._tasks if t is not asyncio.current_task()]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    async def _track(self, name: str, coro) -> None:
        task = asyncio.current_task()
        self._tasks.add(task)
        self.connections[name] += 1
        try:
            await coro
        finally:
            self._tasks.discard(task)

    async def _serve_rtde(self, reader, writer) -> None:
        with contextlib.suppress(asyncio.CancelledError):
            await self._track("rtde", RTDESession(self.hub, reader, writer).run())

    async def _serve_dashboard(self, reader, writer) -> None:
        with contextlib.suppress(asyncio.CancelledError):
            await self._track("dashboard", serve_dashboard(self.model, reader, writer, self.dashboard_log,
                                                           self.polyscope, self.serial))

    async def _serve_script(self, reader, writer) -> None:
        with contextlib.suppress(asyncio.CancelledError):
            await self._track("script", serve_script_port(self.model, reader, writer))
