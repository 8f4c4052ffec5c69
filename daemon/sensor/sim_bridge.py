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

Run as a command (`python -m spadscan.daemon.sensor.sim_bridge --help`), the twin stands in for the bridge of a rig
config (`examples/rig-serial.toml`): it prints its port in one line and streams a fixed scene seen from a fixed pose
(it knows no arm) until Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import argparse
import math
import os
import queue
import select
import signal
import sys
import tempfile
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from spadscan.protocol.errors import SpadscanError

FAULTS = ("drop", "duplicate", "swap", "truncate", "garble", "out_of_range", "merge", "no_result", "bad_result")
"""Frame faults `send_frame` can inject; every one of them must make the receiver drop the frame."""


@dataclass
class BridgeResult:
    """The `#Obj` record that closes a frame: temperature (deg C, 0..255: the chip's unsigned byte), the valid-results
    count (None: the slots with a non-zero confidence, as the chip counts them), 36 distances (mm) and confidences
    (slot k: target k // 18 + 1 of channel k % 9 + 1, as `i2c_records` lays them out)."""

    result_no: int = 0
    temperature_c: int = 25
    n_valid: int | None = None
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
    """The `#Obj` line as ams' Arduino print_results prints it and the UW firmware sends it: 78 fields, no trailing
    comma, ended by '\\n' (the firmware's PRINT_LN); the temperature byte printed unsigned."""
    if not 0 <= result.temperature_c <= 255:
        raise ValueError(f"bridge temperature {result.temperature_c} C: the chip reports an unsigned byte, 0..255")
    pairs = [v for d, c in zip(result.distances_mm, result.confidences) for v in (d, c)]
    n_valid = sum(1 for c in result.confidences if c) if result.n_valid is None else result.n_valid
    head = [address, result.result_no, result.temperature_c, n_valid, result.systick]
    return ("#Obj," + ",".join(map(str, head + pairs)) + "\n").encode()


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

    def boot(self, active_range: int = 0x6E, *, start_s: float = 0.0) -> None:
        """Queue what the UW bridge prints as it starts, before any record: the application's version as it downloads
        it ("#Vers,a.b.c.d"), "FW downloaded" after it downloaded the sensor's firmware, then the sensor's ACTIVE_RANGE
        in hex (Arduino's print(x, HEX): no leading zero), each
        line ended by '\\n' as the firmware ends them. `start_s`: the time between the two lines (what is queued
        later waits behind it), where the firmware sends the short-range command and waits 4 s, runs a factory
        calibration, configures the sensor and starts measuring (`serial_bridge.BRIDGE_START_S`)."""
        self._queue.put(("data", b"#Vers,1.20.0.30\n" + b"FW downloaded\n"))
        if start_s > 0:
            self._queue.put(("pause", float(start_s)))
        self._queue.put(("data", f"Active range: {active_range:X}\n".encode()))

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
        if not self._mark().wait(timeout_s):
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
                for line in lines:
                    if stop.wait(line_s):
                        return
                    self._queue.put(("data", line))
                written = self._written_at(stop)
                if written is None:
                    return
                # The result's interrupt was cleared before its line was read and printed: the next frame is up.
                # Counted from the line's real write, so that this thread's own lateness on a busy machine moves
                # the chip's timeline instead of breaking the bridge's promptness that the sensor's bound assumes.
                handover = written - line_s
                last = j

        self._stream = threading.Thread(target=run, name="spadscan-sim-bridge-chip", daemon=True)
        self._stream.start()

    def _mark(self) -> threading.Event:
        """An event the writer sets once it has written everything queued before it."""
        done = threading.Event()
        self._queue.put(("mark", done))
        return done

    def _written_at(self, stop: threading.Event) -> float | None:
        """When the writer has written everything queued so far (time.monotonic()), or None once `stop` is set."""
        done = self._mark()
        while not done.wait(0.05):
            if stop.is_set():
                return None
        return time.monotonic()

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
            elif kind == "pause":
                self._closing.wait(arg)  # close ends it at once

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
        if self._slave is not None and _link_target(self.port) == os.ttyname(self._slave):  # not another twin's
            os.unlink(self.port)
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None


# ---- the twin as a command ---------------------------------------------------------------------------------------
PROG = "python -m spadscan.daemon.sensor.sim_bridge"
UNREAD_WRITE_TIMEOUT_S = 0.02
"""The command's write timeout: a frame nobody reads (no daemon has the port open) is dropped at once, as a USB
bridge's output is lost, instead of piling up behind the pty's full buffer and arriving stale later."""


class FixedView:
    """counts (10, 128) for the bridge: the scene's expected photon rates from one fixed sensor pose, computed once,
    with fresh photon noise drawn for every frame (`simulator`: a protocol `Simulator`)."""

    def __init__(self, simulator, pose: np.ndarray):
        self._sim = simulator
        self._rates = simulator.expected_rates(pose[None])
        self._reference = simulator.reference_rates(1)

    def __call__(self) -> np.ndarray:
        hists = self._sim.draw_counts(self._rates)[0][0]
        reference = None if self._reference is None else \
            self._sim.draw_counts(self._reference, self._sim.reference_rng)[0][0]
        return bridge_counts(hists, reference)


def fixed_view(mesh_spec: str, distance_m: float, elevation_deg: float, seed: int) -> FixedView:
    """The TMF8820 preset looking at the centre of the mesh's bounding box from distance_m away, elevation_deg above
    its horizontal plane (from +x). Imports the simulator here: importing the twin for tests costs none of it."""
    from spadscan.protocol.mesh_io import load_mesh_spec
    from spadscan.protocol.schedules import look_at
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import Simulator

    mesh, _ = load_mesh_spec(mesh_spec)
    centre = np.asarray(mesh.bounds, dtype=np.float64).mean(axis=0)
    el = math.radians(elevation_deg)
    eye = centre + distance_m * np.array([math.cos(el), 0.0, math.sin(el)])
    return FixedView(Simulator(mesh, sensor_preset("tmf8820"), seed=seed), look_at(eye, centre))


class OneLineParser(argparse.ArgumentParser):
    """Usage errors in one line (the usage itself is in --help)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _number(kind, lo: float, hi: float, unit: str):
    """An argparse type: a finite `kind` (int or float) in [lo, hi], refused in words naming the range."""
    what, span = ("a number", f"[{lo:g}, {hi:g}]{unit}") if kind is float else ("a whole number", f"[{lo}, {hi}]{unit}")

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not (math.isfinite(value) and lo <= value <= hi):
            raise argparse.ArgumentTypeError(f"{text!r} is not {what} in {span}")
        return value
    return parse


def _link_target(path: str) -> str | None:
    """Where the link `path` points, or None when it is no link (or gone)."""
    try:
        return os.readlink(path)
    except OSError:
        return None


def _folder(text: str) -> str:
    """A folder, made where it is missing, as an absolute path: the printed port goes into a config, which reads
    paths from its own folder."""
    try:
        os.makedirs(text, exist_ok=True)
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"{text!r} is no folder that can be made ({exc.strerror or exc})") from None
    return os.path.abspath(text)


def _port_taken(directory: str | None) -> str | None:
    """Why the twin may not serve in `directory`: its port there leads to a pty that is open (another twin's, still
    running); None otherwise (a link a killed twin left leads nowhere, and is replaced)."""
    if directory is None:
        return None
    port = os.path.join(directory, "ttyBRIDGE")
    target = _link_target(port)
    if target is None or not os.path.exists(target):
        return None
    return (f"{port} is the port of a twin still running (its pty {target} is open): stop it, or give another "
            f"--dir")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog=PROG,
        description="The simulated Arduino bridge of a serial TMF8820, on a pseudo-terminal: rehearse a rig config "
                    "with [sensor] backend = \"serial\" without the hardware.",
        epilog="It prints its port in one line; set the config's [sensor] port to it (and bridge_period_ms to "
               "--period-ms). It knows no arm: every frame renders the same scene from the same fixed pose "
               "(--distance-m from the centre of the scene's bounding box, --elevation-deg above it), with fresh "
               "photon noise, in the bridge's #Raw/#Obj lines (the #Obj lines carry no on-chip distances). So a "
               "scan records real bridge traffic that does not follow the arm: it rehearses the link and the "
               "rig, not a reconstruction. "
               "Frames nobody reads are dropped, as a USB bridge's are. Ctrl-C or SIGTERM stops it.")
    parser.add_argument("--dir", type=_folder, default=None,
                        help="folder for the port (made if missing), DIR/ttyBRIDGE, a link to the pty (like "
                             "/dev/serial/by-id/...), "
                             "so that a config keeps one path across runs (default: a new temporary folder)")
    parser.add_argument("--mesh", default="builtin:demo", metavar="SPEC",
                        help="the scene: a mesh file (metres; STL in millimetres is detected) or builtin:NAME "
                             "(any built-in scene `spadscan simulate --help` lists; default builtin:demo)")
    parser.add_argument("--distance-m", type=_number(float, 0.01, 10.0, " m"), default=0.25,
                        help="distance of the fixed sensor pose from the scene's centre, m (default 0.25, the "
                             "radius_m of examples/rig-serial.toml)")
    parser.add_argument("--elevation-deg", type=_number(float, -90.0, 90.0, " deg"), default=45.0,
                        help="elevation of the fixed sensor pose above the scene centre's horizontal plane, "
                             "degrees (default 45)")
    # At 50 ms a frame nobody reads is dropped before the next one is due; a real bridge needs ~140 ms to print one.
    parser.add_argument("--period-ms", type=_number(int, 50, 65535, " ms"), default=230,
                        help="frame period, ms, as the bridge firmware's PERIOD (50-65535; default 230, the UW "
                             "firmware's and the daemon's default bridge_period_ms)")
    parser.add_argument("--seed", type=_number(int, 0, 2**32 - 1, ""), default=0,
                        help="seed of the photon noise (default 0)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _run(args)
    except KeyboardInterrupt:  # Ctrl-C while the scene was being built: nothing was opened yet
        return 130


def _run(args: argparse.Namespace) -> int:
    taken = _port_taken(args.dir)
    if taken is not None:
        print(f"{PROG}: error: {taken}", file=sys.stderr)
        return 1
    try:
        source = fixed_view(args.mesh, args.distance_m, args.elevation_deg, args.seed)
    except (SpadscanError, OSError, ValueError) as exc:
        said = str(exc) if args.mesh in str(exc) else f"--mesh {args.mesh}: {exc}"
        print(f"{PROG}: error: {said}", file=sys.stderr)
        return 1
    with SimBridge(args.dir, write_timeout_s=UNREAD_WRITE_TIMEOUT_S) as bridge:
        bridge.start_stream(source, args.period_ms / 1000)
        _serve_until_stopped(f"bridge twin on {bridge.port} ({os.path.realpath(bridge.port)}): "
                             f"set [sensor] port = \"{bridge.port}\" (Ctrl-C stops it)")
        frames = bridge.counts["frames"]
    print(f"bridge twin stopped after {frames} frames", flush=True)
    return 0


STOP_POLL_S = 0.1
"""How often the twin's main thread looks whether a signal asked it to stop."""


def _serve_until_stopped(ready: str) -> None:
    """Say `ready` and wait for Ctrl-C or SIGTERM; the stream runs in its own threads. Both handlers are set here,
    before `ready` is said (a signal sent as soon as it is read finds them): a shell that starts the twin in the
    background (`... &`) hands it SIGINT ignored, and the twin still stops on `kill -INT`.

    The main thread sleeps in short naps rather than waiting on an event: the kernel may hand the signal to one of
    the stream's threads, which leaves a main thread blocked on a lock asleep for good (Python runs the handler only
    when the main thread next runs), and a handler that set an event could deadlock on the event's own lock. The
    handler only notes the signal."""
    caught: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, _: caught.append(signum))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        print(ready, flush=True)
        while not caught:
            time.sleep(STOP_POLL_S)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


if __name__ == "__main__":
    sys.exit(main())
