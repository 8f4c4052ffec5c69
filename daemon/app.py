"""The daemon process: devices up (in parallel), the control socket, the scan runner; a clean shutdown on SIGTERM,
SIGINT, SIGHUP or `ctl shutdown`.

Start-up order keeps anything from moving before the whole config is known good: config and default scan plan
checked, devices built, socket path claimed, captures root locked (one daemon per root), then devices connected and
prepared. Whatever happens afterwards, the
runner stops the arm and records the scan's state, every device is released and closed, and the socket file goes.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import time

from spadscan.protocol.capture_format import fold
from spadscan.protocol.errors import ConfigError, DeviceError

from .config import DaemonConfig, check_captures_creatable, make_captures
from .client import ControlError, call
from .control import ControlServer, SocketServed, check_socket_path, claim_socket_path
from .devices import Device
from .rig import build_devices, preflight, rig_record
from .root_lock import RootLock, check_root_free
from .runner import ScanRunner
from .scan_end import ScanEnd
from .scan_plan import build_plan

log = logging.getLogger("spadscan.daemon")
STEP_TIMEOUT_S = {"connect": 30.0, "prepare": 60.0, "release": 15.0, "close": 15.0}


class DeviceSession:
    """`async with DeviceSession([arm, sensor])`: connect and prepare all devices in parallel; on the way out
    release and close all of them, always. A failure of any device is one DeviceError naming every device that
    failed and in which step."""

    def __init__(self, devices: list[Device], timeouts: dict[str, float] | None = None):
        self.devices = devices
        self.timeouts = {**STEP_TIMEOUT_S, **(timeouts or {})}

    async def _step(self, device: Device, step: str) -> None:
        timeout = self.timeouts[step]
        try:
            async with asyncio.timeout(timeout):
                await getattr(device, step)()
        except TimeoutError:
            raise DeviceError(f"{device.name}: {step} did not finish within {timeout:g} s") from None
        if step == "connect":  # a controller or bridge that answers late held the start-up: say when each came up
            log.info("%s connected", device.name)

    async def _all(self, step: str) -> list[str]:
        results = await asyncio.gather(*(self._step(d, step) for d in self.devices), return_exceptions=True)
        failures = []
        for device, result in zip(self.devices, results):
            if isinstance(result, asyncio.CancelledError):
                raise result
            if isinstance(result, BaseException):
                text = str(result) if isinstance(result, DeviceError) else \
                    f"{device.name}: {step} failed: {type(result).__name__}: {result}"
                failures.append(text)
        return failures

    async def __aenter__(self) -> "DeviceSession":
        try:
            failures = await self._all("connect")
            if not failures:
                failures = await self._all("prepare")
        except asyncio.CancelledError:  # a stop during start-up: what connected so far is released and closed
            await self._down()
            raise
        if failures:
            await self._down()
            raise DeviceError("rig did not start: " + "; ".join(failures))
        return self

    async def _down(self) -> list[str]:
        return await self._all("release") + await self._all("close")

    async def __aexit__(self, exc_type, exc, tb) -> None:
        failures = await self._down()
        if failures:
            log.error("rig did not shut down cleanly: %s", "; ".join(failures))
            if exc_type is None:
                raise DeviceError("rig did not shut down cleanly: " + "; ".join(failures))


class Dispatcher:
    """Turns control requests into runner calls."""

    OPS = {"status": (), "scan": ("name", "options"), "pause": (), "resume": ("name",), "abort": ("reason", "name"),
           "wait": ("name",), "shutdown": ()}

    def __init__(self, runner: ScanRunner, stop: asyncio.Event, cfg: DaemonConfig):
        self.runner, self.stop, self.cfg = runner, stop, cfg
        self.started = time.monotonic()

    async def __call__(self, req: dict) -> dict:
        op = req["op"]
        if op not in self.OPS:
            raise ConfigError(f"unknown op {op!r} (known: {', '.join(self.OPS)})")
        extra = set(req) - {"op", *self.OPS[op]}
        if extra:
            raise ConfigError(f"op {op!r} takes no {', '.join(sorted(extra))}")
        r = self.runner
        await r.aborts.retry()  # each request writes again an abort the disk could not take yet
        if op in ("resume", "abort") and not isinstance(req.get("name", ""), str):
            raise ConfigError(f"{op}'s 'name' must be a scan name (a string)")
        named = {"name": req["name"]} if req.get("name") else {}  # a scan the daemon does not hold (see ScanRunner)
        if op == "status":
            return {**await r.status_now(), "daemon": self._daemon(time.monotonic())}
        if op == "scan":
            options = req.get("options", {})
            if not isinstance(options, dict):
                raise ConfigError("scan options must be a JSON object of [scan] keys")
            return await r.start(req.get("name"), options)
        if op == "pause":
            return await r.pause()
        if op == "resume":
            return await r.resume(**named)
        if op == "abort":
            # On one line before the cut: the capture records it as one line, and status and logs show it too.
            return await r.abort(fold(req.get("reason") or "")[:200] or "aborted by user", **named)
        if op == "wait":
            if not isinstance(req.get("name"), str):
                raise ConfigError("wait needs a scan 'name'")
            return self._wait_reply(req["name"], await r.wait_end(req["name"]))
        asyncio.get_running_loop().call_soon(self.stop.set)  # after the reply is written
        return {"stopping": True}

    def _daemon(self, at: float) -> dict:
        """The daemon's own block of a status, as it stood at `at` (time.monotonic())."""
        return {"pid": os.getpid(), "socket": str(self.cfg.socket), "captures": str(self.cfg.captures),
                "uptime_s": round(max(0.0, at - self.started), 1)}

    def _wait_reply(self, name: str, end: ScanEnd) -> dict:
        """`wait`'s reply: {"name", "state", "reason" (why it ended so, where a reason was given: `ctl wait` says it),
        "status": the daemon's status as the scan ended (what `ctl wait --json` prints), null for a scan that ended
        before this daemon started}."""
        status = None if end.status is None else {**end.status, "daemon": self._daemon(end.at)}
        return {"name": name, "state": end.state, **({"reason": end.reason} if end.reason else {}), "status": status}


def check_config(cfg: DaemonConfig):
    """Everything start-up checks before a device is touched, creating, claiming and holding nothing (`spadscan
    daemon --check` runs them through `check_only`): the default scan plan, the devices built (a sim sensor's mesh
    loaded, the sensor model), an I2C sensor's firmware image read and parsed, its bus or a serial sensor's port
    present, the socket path neither taken by another file nor served by another daemon, the captures root not held
    by another daemon and, when it does not exist yet, one that can be created (tried: a scratch folder made and
    removed). Returns (plan, arm, sensor), neither device connected."""
    plan, arm, sensor = _check_rig(cfg)
    _in_config(cfg, check_socket_path, cfg.socket)
    _check_root(cfg)
    return plan, arm, sensor


def check_only(cfg: DaemonConfig):
    """`spadscan daemon --check`: check_config's checks, where a daemon already serving the config's socket is no
    error (the config is valid all the same; only a start would be refused): the captures root is checked as ever
    unless that daemon holds it (the config's own daemon, running), as its `status` says. Returns (plan, None), or
    (plan, 'a daemon is already running on SOCKET (pid N)', naming its captures root where it is not the config's);
    ConfigError for anything else, a daemon on the socket that does not answer `status` included."""
    plan, _, _ = _check_rig(cfg)
    served = _in_config(cfg, _served, cfg.socket)
    if served is None:
        _check_root(cfg)
        return plan, None
    try:
        daemon = call(cfg.socket, "status", STATUS_CHECK_S).get("daemon")
    except ControlError as why:
        raise ConfigError(f"{cfg.source}: {served}; it did not answer `status`: {why}") from None
    daemon = daemon if isinstance(daemon, dict) else {}
    said = [f"pid {daemon['pid']}"] if daemon.get("pid") is not None else []
    if not _same_folder(daemon.get("captures"), cfg.captures):
        _check_root(cfg)
        said += [f"captures root {daemon['captures']}"] if daemon.get("captures") else []
    return plan, f"a daemon is already running on {cfg.socket}" + (f" ({', '.join(said)})" if said else "")


STATUS_CHECK_S = 5.0
"""How long `--check` waits for the status of a daemon serving the config's socket: a status waits at most
`runner.SLIDER_READ_S` (1 s) for the arm's speed slider, the rest is quick."""


def _check_rig(cfg: DaemonConfig):
    """The default scan plan, the devices built, each backend's preflight: (plan, arm, sensor)."""
    plan = build_plan(cfg.scan, cfg.arm, where=f"{cfg.source}: [scan] defaults")
    arm, sensor = build_devices(cfg)
    preflight(cfg)
    return plan, arm, sensor


def _served(path) -> SocketServed | None:
    """check_socket_path(path)'s refusal of a socket that a daemon of this user serves, returned (None: the path is
    free); any other refusal is raised."""
    try:
        check_socket_path(path)
    except SocketServed as exc:
        return exc
    return None


def _check_root(cfg: DaemonConfig) -> None:
    """The captures root held by no daemon and, when it does not exist yet, one that start-up can create."""
    _in_config(cfg, check_root_free, cfg.captures)
    _in_config(cfg, check_captures_creatable, cfg.captures)


def _same_folder(a, b) -> bool:
    """Whether paths a and b name one existing folder (a link to it included); False when either is missing."""
    try:
        return a is not None and os.path.samefile(a, b)
    except (OSError, TypeError, ValueError):
        return False


def _in_config(cfg: DaemonConfig, check, *args):
    """check(*args), its ConfigError prefixed with the config file, as every other config error is."""
    try:
        return check(*args)
    except ConfigError as exc:
        raise ConfigError(f"{cfg.source}: {exc}") from None


def check_startup(cfg: DaemonConfig) -> tuple[Device, Device, RootLock]:
    """Everything that can be checked before a device is touched, then the captures root created and locked and
    the socket path claimed; returns (arm, sensor, lock): the devices not yet connected, the lock held (release
    it when the daemon ends)."""
    _, arm, sensor = check_config(cfg)
    _in_config(cfg, make_captures, cfg.captures)
    _in_config(cfg, claim_socket_path, cfg.socket)
    lock = RootLock(cfg.captures)
    _in_config(cfg, lock.acquire)
    return arm, sensor, lock


STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
"""Each ends the daemon cleanly. SIGHUP too: it is what a foreground daemon gets when its SSH session drops, and
its default action would kill the daemon with the arm moving and the scan left unrecorded."""


async def serve(cfg: DaemonConfig, arm, sensor, lock: RootLock | None = None) -> None:
    """Run the daemon until SIGTERM, SIGINT, SIGHUP or `ctl shutdown`. The caller has run check_startup and holds
    its `lock`, which each new scan checks is still the captures root's (None: not checked)."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    me = asyncio.current_task()
    # "starting" until the daemon listens: a stop signal then ends the start-up itself (a connect takes up to a
    # minute) by cancelling it, once ("cancelled").
    phase = "starting"

    def on_signal(sig: signal.Signals) -> None:
        nonlocal phase
        log.info("%s received", sig.name)
        stop.set()
        if phase == "starting":
            phase = "cancelled"
            me.cancel()

    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, on_signal, sig)
    try:
        async with DeviceSession([arm, sensor]):
            rig, scene = rig_record(cfg)
            runner = ScanRunner(arm, sensor, cfg, rig=rig, scene=scene, root_lock=lock)
            try:
                await runner.recover()  # before listening: the first `status` already shows an interrupted scan
                phase = "serving"
                if stop.is_set():  # asked to stop while it started: no socket, no scan taken further
                    return
                async with ControlServer(cfg.socket, Dispatcher(runner, stop, cfg)):
                    log.info("listening on %s (captures in %s)", cfg.socket, cfg.captures)
                    await stop.wait()
                    log.info("shutting down")
            finally:
                await runner.shutdown()
    except asyncio.CancelledError:
        if not (phase == "cancelled" and me.cancelling()):
            raise
        me.uncancel()
        log.info("stopped while starting: the devices were released and closed")
    finally:
        for sig in STOP_SIGNALS:
            loop.remove_signal_handler(sig)
