"""A simulated Arduino bridge: writes TMF8820 records as bridge-format lines into a pseudo-terminal.

pyserial opens `SimBridge.port`, a symlink to the current pty (like a udev /dev/serial/by-id link), so a
`SerialSensor` talks to it exactly as to a USB bridge. Faults for tests and the demo: corrupt or partial lines,
frames with a sub-packet missing, duplicated or out of order, a mid-line start, and unplug/replug (the pty is closed
and the link removed; a replug opens a new pty behind the same link). All writes happen in one writer thread in the
order they were queued; `close` is prompt: what is still queued or half-written is dropped (counted in
`bytes_dropped`, as an unplug loses it), waiters in `flush` are let go, the thread stops and every descriptor closes.

`start_measuring` models the bridge's timing on a chip that measures cyclically (the UW firmware's loop: clear a
record's interrupt, read the record, print its line; the chip hands the next record over after the clear, and keeps
the latest finished measurement in a one-frame buffer) and records when each frame's measurement was exposed.
"""

from __future__ import annotations

import os
import queue
import select
import tempfile
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

FAULTS = ("drop", "duplicate", "swap", "truncate", "garble", "out_of_range", "merge", "no_result", "bad_result")
"""Frame faults `send_frame` can inject; every one of them must make the receiver drop the frame."""


@dataclass
class BridgeResult:
    """The `#Obj` record that closes a frame: temperature (deg C), 36 distances (mm) and confidences."""

    result_no: int = 0
    temperature_c: int = 25
    n_valid: int = 9
    systick: int = 0
    distances_mm: list[int] = field(default_factory=lambda: [0] * 36)
    confidences: list[int] = field(default_factory=lambda: [0] * 36)


def raw_lines(counts: np.ndarray, address: int = 0x41) -> list[bytes]:
    """The 30 `#Raw` lines for counts (10, 128) < 2**24: line n carries byte plane n // 10 of channel n % 10."""
    c = np.asarray(counts, dtype=np.int64)
    if c.shape != (10, 128) or c.min() < 0 or c.max() >= 1 << 24:
        raise ValueError(f"bridge counts must be (10, 128) in [0, 2**24), got {c.shape}")
    lines = []
    for n in range(30):
        plane = (c[n % 10] >> (8 * (n // 10))) & 0xFF
        lines.append(f"#Raw,{address},{n},".encode() + ",".join(map(str, plane.tolist())).encode() + b"\n")
    return lines


def obj_line(result: BridgeResult, address: int = 0x41) -> bytes:
    """The `#Obj` line (78 fields, trailing comma as the bridge prints it; the temperature byte printed unsigned)."""
    if not -128 <= result.temperature_c <= 127:
        raise ValueError(f"bridge temperature {result.temperature_c} C is outside a signed byte [-128, 127]")
    pairs = [v for d, c in zip(result.distances_mm, result.confidences) for v in (d, c)]
    head = [address, result.result_no, result.temperature_c & 0xFF, result.n_valid, result.systick]
    return ("#Obj," + ",".join(map(str, head + pairs)) + ",\r\n").encode()


def bridge_counts(hists: np.ndarray, reference: np.ndarray | None) -> np.ndarray:
    """Counts (10, 128) for the bridge from zone histograms (9, 128) and a reference (128,), clipped to 24 bits."""
    ref = np.zeros(hists.shape[1], np.int64) if reference is None else np.asarray(reference, np.int64)
    return np.clip(np.vstack([ref[None], np.asarray(hists, np.int64)]), 0, (1 << 24) - 1)


def frame_lines(counts: np.ndarray, result: BridgeResult, fault: str | None = None, at: int = 7,
                address: int = 0x41) -> list[bytes]:
    """The lines of one frame, with `fault` (one of FAULTS) injected at sub-packet `at` (1..28)."""
    lines = raw_lines(counts, address)
    last = obj_line(result, address)
    if fault is None:
        return lines + [last]
    if fault not in FAULTS or not 1 <= at <= 28:
        raise ValueError(f"fault {fault!r} at {at}: expected one of {FAULTS} at sub-packet 1..28")
    if fault == "drop":
        del lines[at]
    elif fault == "duplicate":
        lines.insert(at, lines[at])
    elif fault == "swap":
        lines[at], lines[at + 1] = lines[at + 1], lines[at]
    elif fault == "truncate":
        lines[at] = lines[at][: len(lines[at]) // 2] + b"\n"
    elif fault == "garble":
        fields = lines[at].split(b",")
        fields[60] = b"1x"  # line noise turned a digit into another byte
        lines[at] = b",".join(fields)
    elif fault == "out_of_range":
        lines[at] = lines[at].rpartition(b",")[0] + b",256\n"
    elif fault == "merge":
        lines[at] = lines[at].rstrip(b"\n")
    elif fault == "no_result":
        last = b"#Obj\n"  # only the separator: the frame never gets its result
    elif fault == "bad_result":
        last = last[: len(last) // 2] + b"\n"
    return lines + [last]


class SimBridge:
    """The bridge twin. `port` is the path to open; sends are queued and written by one thread, in order."""

    def __init__(self, directory: str | os.PathLike | None = None, *, address: int = 0x41,
                 write_timeout_s: float = 5.0):
        self._own_dir = directory is None
        self.directory = Path(tempfile.mkdtemp(prefix="spadscan-bridge-") if directory is None else directory)
        self.port = str(self.directory / "ttyBRIDGE")
        self.address = address
        self.write_timeout_s = write_timeout_s
        self.counts = {"frames": 0, "bytes": 0, "bytes_dropped": 0, "unplugs": 0, "replugs": 0}
        self.exposures: dict[int, tuple[float, float]] = {}
        """start_measuring: measurement number (its frame's systick) -> (begin, end) of its exposure, monotonic s."""
        self._master: int | None = None
        self._slave: int | None = None
        self._queue: queue.Queue = queue.Queue()
        self._stream_stop = threading.Event()
        self._closing = threading.Event()  # set by close: the writer drops instead of waiting for a reader
        self._stream: threading.Thread | None = None
        self._plug()
        self._writer = threading.Thread(target=self._write_loop, name="spadscan-sim-bridge", daemon=True)
        self._writer.start()

    # ---- what tests and the demo call ----------------------------------------------------------------------------
    def send(self, data: bytes) -> None:
        """Queue raw bytes (e.g. the tail of a line, for a mid-line start)."""
        self._queue.put(("data", bytes(data)))

    def boot(self, active_range: int = 0x6E) -> None:
        """Queue what the UW bridge prints as it starts, before any record: "FW downloaded" after it downloaded the
        sensor's firmware, then the sensor's ACTIVE_RANGE in hex (Arduino's print(x, HEX): no leading zero)."""
        self._queue.put(("data", f"FW downloaded\r\nActive range: {active_range:X}\r\n".encode()))

    def send_frame(self, counts: np.ndarray, result: BridgeResult | None = None, fault: str | None = None,
                   at: int = 7) -> None:
        """Queue one frame: counts (10, 128) (channel 0 = reference), its result, and an optional fault."""
        lines = frame_lines(counts, result or BridgeResult(), fault, at, self.address)
        self.counts["frames"] += 1
        self._queue.put(("data", b"".join(lines)))

    def unplug(self) -> None:
        """Queue an unplug: the pty closes and the port path disappears."""
        self._queue.put(("unplug", None))

    def replug(self) -> None:
        """Queue a replug: a new pty appears behind the same port path."""
        self._queue.put(("replug", None))

    def flush(self, timeout_s: float = 10.0) -> None:
        """Wait until everything queued so far is written (not necessarily read)."""
        if self._closing.is_set():
            raise RuntimeError("sim bridge: flush after close")
        done = threading.Event()
        self._queue.put(("mark", done))
        if not done.wait(timeout_s):
            raise TimeoutError(f"sim bridge: queued writes not done within {timeout_s} s")

    def start_stream(self, source: Callable[[], np.ndarray], period_s: float, *, fault_every: int = 0) -> None:
        """Send a frame from `source()` (counts (10, 128)) every period_s seconds in a thread, until stop_stream.

        fault_every > 0 injects the faults of FAULTS in turn into every fault_every-th frame.
        """
        self.stop_stream()
        self._stream_stop.clear()

        def run():
            k = 0
            next_t = time.monotonic()
            while not self._stream_stop.wait(max(0.0, next_t - time.monotonic())):
                k += 1
                fault = FAULTS[(k // fault_every) % len(FAULTS)] if fault_every and k % fault_every == 0 else None
                self.send_frame(source(), BridgeResult(result_no=k % 256, systick=k), fault)
                next_t += period_s

        self._stream = threading.Thread(target=run, name="spadscan-sim-bridge-stream", daemon=True)
        self._stream.start()

    def start_measuring(self, source: Callable[[], np.ndarray], period_s: float, *, line_s: float = 0.005,
                        exposure_s: float | None = None) -> None:
        """Stream like the UW bridge on a chip measuring cyclically from now (t0), until stop_stream.

        Measurement j is exposed over [t0 + (j + 1) period_s - exposure_s, t0 + (j + 1) period_s] (exposure_s:
        default the whole period, the longest it can take). When the bridge clears the interrupt of a frame's result
        (before it reads and prints that line) the chip hands over the latest measurement finished by then and not
        sent yet, or the next one when it finishes; each of the frame's 31 lines then takes line_s (reading the
        record over I2C and printing it). Frame j carries systick j and result number j % 256; `exposures[j]` is its
        exposure. counts (10, 128) come from `source()`.
        """
        exposure = period_s if exposure_s is None else exposure_s
        if not (period_s > 0 and 0 <= exposure <= period_s and line_s >= 0):
            raise ValueError(f"period {period_s} s, exposure {exposure} s and line time {line_s} s: need "
                             f"0 <= exposure <= period, period > 0, line time >= 0")
        self.stop_stream()
        self._stream_stop.clear()
        t0 = time.monotonic()
        stop = self._stream_stop

        def run():
            handover, last = t0, -1  # the chip hands over the next frame at `handover`
            while True:
                j = max(int((handover - t0) // period_s) - 1, last + 1)  # the latest finished, else the next
                end = t0 + (j + 1) * period_s
                if stop.wait(max(0.0, end - time.monotonic())):
                    return
                self.exposures[j] = (end - exposure, end)
                lines = frame_lines(source(), BridgeResult(result_no=j % 256, systick=j), address=self.address)
                self.counts["frames"] += 1
                for k, line in enumerate(lines):
                    if k == len(lines) - 1:
                        handover = time.monotonic()  # the result's interrupt is cleared: the next frame is up
                    if stop.wait(line_s):
                        return
                    self._queue.put(("data", line))
                last = j

        self._stream = threading.Thread(target=run, name="spadscan-sim-bridge-chip", daemon=True)
        self._stream.start()

    def stop_stream(self) -> None:
        if self._stream is not None:
            self._stream_stop.set()
            self._stream.join()
            self._stream = None

    def close(self) -> None:
        """Stop the threads, drop what is still queued, close the pty and remove the port path (promptly: within
        one select period, never a write timeout)."""
        self.stop_stream()
        self._closing.set()
        if self._writer.is_alive():
            self._queue.put(("quit", None))
            self._writer.join()
        self._drop_queued()
        self._unplug()
        if self._own_dir:
            try:
                self.directory.rmdir()
            except OSError:
                pass

    def __enter__(self) -> "SimBridge":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- the writer thread ---------------------------------------------------------------------------------------
    def _write_loop(self) -> None:
        while True:
            kind, arg = self._queue.get()
            if kind == "quit":
                return
            if kind == "data":
                if self._closing.is_set():
                    self.counts["bytes_dropped"] += len(arg)
                else:
                    self._write(arg)
            elif kind == "unplug":
                self._unplug()
                self.counts["unplugs"] += 1
            elif kind == "replug":
                self._plug()
                self.counts["replugs"] += 1
            elif kind == "mark":
                arg.set()

    def _write(self, data: bytes) -> None:
        """Write to the pty master, waiting for the reader to drain it; drop the rest after write_timeout_s."""
        view = memoryview(data)
        deadline = time.monotonic() + self.write_timeout_s
        while view:
            if self._master is None or time.monotonic() > deadline or self._closing.is_set():
                # unplugged, nobody reads, or closing: the data is lost
                self.counts["bytes_dropped"] += len(view)
                return
            _, ready, _ = select.select([], [self._master], [], 0.05)
            if not ready:
                continue
            try:
                n = os.write(self._master, view[:4096])
            except BlockingIOError:
                continue
            except OSError:
                self.counts["bytes_dropped"] += len(view)
                return
            self.counts["bytes"] += n
            view = view[n:]

    def _drop_queued(self) -> None:
        """After the writer stopped: count what it never wrote as dropped and let every flush waiter go."""
        while True:
            try:
                kind, arg = self._queue.get_nowait()
            except queue.Empty:
                return
            if kind == "data":
                self.counts["bytes_dropped"] += len(arg)
            elif kind == "mark":
                arg.set()

    def _plug(self) -> None:
        if self._master is not None:
            return
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing: bytes pass through as a USB CDC port passes them
        os.set_blocking(master, False)
        tmp = self.port + ".new"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.port)
        self._master, self._slave = master, slave

    def _unplug(self) -> None:
        if os.path.lexists(self.port):
            os.unlink(self.port)
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None
