"""The TMF8820 as a `Sensor`: frame assembly and health over any transport, in one dedicated reader thread.

The reader thread runs from `prepare` to `release`: it reads packets as they arrive (so that arrival times are
true even while nobody asks for frames, e.g. while the arm moves), assembles frames and queues them for
`next_frame`. When the link fails it closes the transport and reopens it with exponential backoff; `next_frame`
raises `LinkLost` only once the link has been down longer than `link_grace_s`, and frames flow again after a
replug. All transport calls (open, start, reads, restart, stop, close) run in that same thread, one at a time.

`begin_exposure` (the arm has settled) restarts the measurement on a transport that can (I2C): the reader thread
stops it and starts a fresh one between two reads, and the frame in progress and the frames queued, all measured
before, are discarded. A bridge measures on its own and cannot be restarted; its frames' `t_start` counts back from
the previous record's arrival by the assembler's timing model (`assembly.FrameAssembler`).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import threading
import time
from concurrent.futures import Future, InvalidStateError, ThreadPoolExecutor

from spadscan.daemon.devices import Frame, LinkLost, Sensor, SensorSilent
from spadscan.protocol.errors import DeviceError, SpadscanError
from spadscan.protocol.sensor_model import SensorModel
from spadscan.protocol.sensor_presets import sensor_preset

from .assembly import FrameAssembler
from .transport import N_CHANNELS, SUBPACKET_BYTES, LinkDown, Transport

log = logging.getLogger("spadscan.daemon")

READ_SLICE_S = 0.05
"""Longest single blocking read, so that the reader notices `release` promptly."""


class TMF8820(Sensor):
    """A TMF8820 (3x3 zones, 128 bins, reference channel) behind `transport`.

    model: the sensor model frames are described by (default: the `tmf8820` preset); it must have 9 zones of 128
    bins. frame_timeout_s: a frame not completed this long after its first sub-packet is dropped. link_grace_s: how
    long the link may be down before `next_frame` raises LinkLost. start_timeout_s: limit for opening and starting
    the link in `connect`/`prepare`. queue_frames: frames kept for `next_frame`; older ones are dropped (counted).
    """

    def __init__(self, transport: Transport, *, model: SensorModel | None = None, frame_timeout_s: float = 2.0,
                 link_grace_s: float = 5.0, start_timeout_s: float = 30.0, queue_frames: int = 256,
                 backoff_s: tuple[float, float] = (0.05, 2.0)):
        self.model = model if model is not None else sensor_preset("tmf8820")
        if self.model.n_zones != N_CHANNELS - 1 or self.model.n_bins != SUBPACKET_BYTES:
            raise DeviceError(f"sensor {transport.name}: a TMF8820 delivers 9 zones x 128 bins, but the sensor model "
                              f"{self.model.name!r} has {self.model.n_zones} zones x {self.model.n_bins} bins")
        if not (link_grace_s >= 0 and start_timeout_s > 0 and queue_frames >= 1):
            raise DeviceError(f"sensor {transport.name}: link grace {link_grace_s} s, start timeout "
                              f"{start_timeout_s} s and queue {queue_frames} frames must be positive")
        self.transport = transport
        self.name = f"sensor {transport.name}"
        self.link_grace_s = link_grace_s
        self.start_timeout_s = start_timeout_s
        self.backoff_s = backoff_s
        self._assembler = FrameAssembler(frame_timeout_s, t0=time.monotonic(), period_s=transport.period_s,
                                         lag_s=transport.arrival_lag_s)
        self._frames: collections.deque[Frame] = collections.deque()
        self._queue_frames = queue_frames
        self._executor: ThreadPoolExecutor | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        self._stop = threading.Event()
        self._reader: asyncio.Future | None = None
        self._restart_request: Future | None = None  # begin_exposure's request, served by the reader thread
        self._connected = False
        self._down_since: float | None = None
        self._failure: BaseException | None = None
        self._stats = {"frames_delivered": 0, "frames_overflowed": 0, "silent_timeouts": 0, "link_drops": 0,
                       "reconnects": 0, "reconnect_failures": 0, "restarts": 0, "frames_discarded_at_restart": 0}
        self._last_error = ""
        self._refused_at_frame = 0  # the transport's bad_records when the last frame was made (or streaming began)

    # ---- lifecycle -----------------------------------------------------------------------------------------------
    async def connect(self) -> None:
        if self._connected:
            return
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        if self._executor is None:
            self._executor = ThreadPoolExecutor(1, thread_name_prefix=f"spadscan-{self.name}")
        try:
            await self._call(self.transport.open, "the link to open")
        except BaseException:
            await self.close()  # leave no thread behind when the device is unusable
            raise
        self._connected = True

    async def prepare(self) -> None:
        if self._reader is not None:
            return
        if not self._connected:
            await self.connect()
        t_start = time.monotonic()
        await self._call(self.transport.start, "the sensor to start measuring")
        # A sensor that measures on its own (a bridge) was not restarted, but its link was emptied in `start`: what
        # is read from now on arrives live, and the first frame counts back from t_start like any other.
        self._assembler.reset(t_start, self.transport.restarts_measurement, drop_first=False)
        self._frames.clear()
        self._stop.clear()
        self._refused_at_frame = self._refused()
        self._reader = self._loop.run_in_executor(self._executor, self._read_loop)

    async def release(self) -> None:
        if self._reader is not None:
            self._stop.set()
            try:
                await asyncio.wait_for(asyncio.shield(self._reader), READ_SLICE_S * 20 + 5.0)
            except asyncio.TimeoutError:
                raise DeviceError(f"{self.name}: reader thread did not stop within "
                                  f"{READ_SLICE_S * 20 + 5.0:.1f} s") from None
            finally:
                self._reader = None
        if self._connected and self._down_since is None:
            await self._call(self.transport.stop, "the sensor to stop measuring", quiet=True)

    async def close(self) -> None:
        if self._reader is not None:
            await self.release()
        if self._executor is not None:
            executor, hung = self._executor, True
            try:
                await self._call(self.transport.close, "the link to close", quiet=True)
                hung = False
            finally:
                self._executor = None
                executor.shutdown(wait=not hung)  # idle unless the close timed out: then do not block the loop
        self._connected = False

    # ---- frames --------------------------------------------------------------------------------------------------
    async def begin_exposure(self) -> float | None:
        """Stop and restart the measurement where the transport can (I2C), discarding every frame measured before;
        returns the monotonic time before the restart (no later frame's exposure began before it), or None: the
        transport measures on its own (a bridge), the sensor is not streaming, or the restart failed (the link is
        then reopened, which restarts the measurement too)."""
        if not self.transport.restarts_measurement or self._reader is None or self._reader.done():
            return None  # not streaming, or the reader stopped (next_frame says why)
        if self._down_since is not None:
            return None  # a link that is down restarts the measurement when it is back
        request: Future = Future()
        self._restart_request = request
        try:
            return await asyncio.wait_for(asyncio.wrap_future(request), self.start_timeout_s)
        except asyncio.TimeoutError:
            raise DeviceError(f"{self.name}: timed out after {self.start_timeout_s:g} s waiting for the sensor to "
                              f"restart its measurement") from None
        finally:
            self._restart_request = None

    async def next_frame(self, timeout_s: float) -> Frame:
        if self._reader is None or self._wake is None:
            raise DeviceError(f"{self.name}: next_frame before prepare (the sensor is not streaming)")
        deadline = time.monotonic() + timeout_s
        while True:
            if self._frames:
                self._stats["frames_delivered"] += 1
                return self._frames.popleft()
            if self._failure is not None:
                raise DeviceError(f"{self.name}: reader stopped: {self._failure}")
            now = time.monotonic()
            down = self._down_since
            if down is not None and now - down >= self.link_grace_s:
                raise LinkLost(f"{self.name}: link down for {now - down:.1f} s (grace {self.link_grace_s:g} s; "
                               f"{self._last_error or 'no detail'}); still trying to reconnect")
            if now >= deadline:
                self._stats["silent_timeouts"] += 1
                detail = self._silent_detail(now)
                raise SensorSilent(f"{self.name}: no complete frame within {timeout_s:g} s"
                                   + (f"; {detail}" if detail else ""), detail)
            self._wake.clear()
            if self._frames or self._failure is not None:
                continue
            wait = deadline - now
            if down is not None:
                wait = min(wait, down + self.link_grace_s - now)
            try:
                await asyncio.wait_for(self._wake.wait(), max(wait, 0.0))
            except asyncio.TimeoutError:
                pass

    def starting_left(self) -> float:
        return self.transport.starting_left(time.monotonic())

    def _silent_detail(self, now: float) -> str:
        """Why frames may have stopped: the error the link reported after the last frame, and the records the
        transport refused since then; '' when neither."""
        parts = []
        down = self._down_since
        if down is not None:  # a pulled cable, a bridge that reset: the silence is the link's, not the chip's
            parts.append(f"the link has been down for {now - down:.1f} s ({self._last_error or 'no detail'}); it "
                         f"reconnects by itself")
        cause = self._assembler.silent_cause
        if cause is not None:
            text, t = cause
            hint = f"; {self.transport.error_hint}" if self.transport.error_hint else ""
            parts.append(f"the bridge reported '{text}' {now - t:.1f} s ago and no frame since{hint}")
        refused = self._refused() - self._refused_at_frame
        if refused > 0:
            last = self.transport.counters().get("last_bad_record")
            were = ("record arrived since the last frame but was" if refused == 1
                    else "records arrived since the last frame but were")
            parts.append(f"{refused} {were} refused (bad_records)"
                         + (f"; the last one: {last}" if last else ""))
        return "; ".join(parts)

    def _refused(self) -> int:
        """Records the transport read and refused so far (its `bad_records` counter; 0 where it keeps none)."""
        return int(self.transport.counters().get("bad_records", 0))

    def counters(self) -> dict:
        out = {**self._assembler.counters(), **self.transport.counters(), **self._stats}
        out["queued"] = len(self._frames)
        out["link"] = "down" if self._down_since is not None else "up"
        starting = self.starting_left()
        if starting > 0:  # the operator sees why no frame comes yet
            out["starting_s"] = round(starting, 1)
        if self._last_error:
            out["last_link_error"] = self._last_error
        return out

    # ---- the reader thread ---------------------------------------------------------------------------------------
    def _read_loop(self) -> None:
        try:
            while not self._stop.is_set():
                request = self._restart_request
                if request is not None and not request.done():
                    self._restart(request)
                    continue
                try:
                    pkt = self.transport.read_packet(READ_SLICE_S)
                except LinkDown as exc:
                    self._link_down(exc)
                    continue
                if pkt is not None:
                    frame = self._assembler.feed(pkt)
                    if frame is not None:
                        self._refused_at_frame = self._refused()
                        self._push(frame)
        except BaseException as exc:  # a bug or an unexpected library error: report it through next_frame
            self._failure = exc
            self._notify()
        finally:
            request = self._restart_request
            if request is not None:
                _answer(request, None)  # released: there is no measurement to restart

    def _restart(self, request: Future) -> None:
        """Stop and restart the measurement (in the reader thread, between two reads); the frames measured before
        are discarded. A failed restart is a dropped link: reopening it starts the measurement afresh."""
        t = time.monotonic()  # the new measurement starts after this: no later exposure began before it
        try:
            self.transport.restart()
        except SpadscanError as exc:
            _answer(request, None)
            self._link_down(exc if isinstance(exc, LinkDown) else LinkDown(f"restart failed: {exc}"))
            return
        discarded = self._assembler.restart(t) + len(self._frames)
        self._frames.clear()  # the runner awaits this restart: nobody takes frames meanwhile
        self._stats["restarts"] += 1
        self._stats["frames_discarded_at_restart"] += discarded
        _answer(request, t)

    def _push(self, frame: Frame) -> None:
        if len(self._frames) >= self._queue_frames:
            self._frames.popleft()
            self._stats["frames_overflowed"] += 1
        self._frames.append(frame)
        self._notify()

    def _notify(self) -> None:
        try:
            self._loop.call_soon_threadsafe(self._wake.set)
        except RuntimeError:  # the loop is closed: nobody is waiting
            pass

    def _link_down(self, exc: Exception) -> None:
        """Close the link and reopen it with exponential backoff until it is back or the device is released."""
        self._stats["link_drops"] += 1
        self._last_error = str(exc)
        self._down_since = time.monotonic()
        log.warning("%s: link lost (%s); reconnecting by itself", self.name, exc)
        self._assembler.reset(self._down_since, restarted=False)  # what the next start says decides
        request = self._restart_request
        if request is not None:
            _answer(request, None)  # the reopened link restarts the measurement itself
        self._notify()
        delay = self.backoff_s[0]
        while not self._stop.is_set():
            self.transport.close()
            t_start = time.monotonic()  # no exposure after a start that restarts the measurement began before this
            try:
                self.transport.open()
                self.transport.start()
            except SpadscanError as err:  # LinkDown, or a boot error after a power loss
                self._stats["reconnect_failures"] += 1
                self._last_error = str(err)
                self._stop.wait(delay)
                delay = min(delay * 2, self.backoff_s[1])
                continue
            self._stats["reconnects"] += 1
            restarted = self.transport.restarts_measurement
            self._assembler.reset(t_start if restarted else time.monotonic(), restarted)
            log.info("%s: link back after %.1f s", self.name, time.monotonic() - self._down_since)
            self._down_since = None
            self._notify()
            return

    async def _call(self, fn, what: str, quiet: bool = False) -> None:
        """Run a blocking transport call in the device's thread, limited to start_timeout_s."""
        fut = self._loop.run_in_executor(self._executor, fn)
        try:
            await asyncio.wait_for(fut, self.start_timeout_s)
        except asyncio.TimeoutError:
            raise DeviceError(f"{self.name}: timed out after {self.start_timeout_s:g} s waiting for {what}") from None
        except SpadscanError as exc:
            if quiet:
                self._last_error = str(exc)
                return
            # Transports word their errors without naming themselves; the device adds its name.
            raise (DeviceError if isinstance(exc, LinkDown) else type(exc))(f"{self.name}: {exc}") from None


def _answer(request: Future, value) -> None:
    """Answer begin_exposure's request unless it stopped waiting (timed out, cancelled)."""
    try:
        request.set_result(value)
    except InvalidStateError:
        pass
