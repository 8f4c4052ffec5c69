"""The bridge twin as a command (`python -m spadscan.daemon.sensor.sim_bridge`): it says where its port is in one
line, serves the bridge's line protocol there to the real pyserial, stops on Ctrl-C with exit 0, and refuses a bad
option in one line."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import threading
import time

import pytest
import serial

from process_helpers import reaped
from spadscan.daemon.sensor.serial_bridge import classify_line
from spadscan.daemon.sensor.transport import HistogramPacket, ResultPacket

COMMAND = [sys.executable, "-m", "spadscan.daemon.sensor.sim_bridge"]
PORT_LINE = re.compile(r'set \[sensor\] port = "([^"]+)"')


def first_record(port: str, max_lines: int = 200) -> HistogramPacket | ResultPacket:
    """The first `#Raw` or `#Obj` record read from `port` that the serial backend accepts (the first line may be cut:
    the port opens mid-stream)."""
    with serial.Serial(port, 1_000_000, timeout=10) as ser:
        for _ in range(max_lines):
            line = ser.readline()
            assert line.endswith(b"\n"), f"no complete line within 10 s: {line[:40]!r}"
            packet = classify_line(line.rstrip(b"\n"), 0.0, 0x41)
            if isinstance(packet, (HistogramPacket, ResultPacket)):
                return packet
    raise AssertionError(f"no well-formed record in {max_lines} lines")


def ignore_sigint() -> None:
    """What a shell does to a command it starts in the background (`... &`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.parametrize("stop, started", [(signal.SIGINT, None), (signal.SIGTERM, None),
                                           (signal.SIGINT, ignore_sigint)], ids=["ctrl-c", "sigterm", "background"])
def test_the_twin_serves_its_port_and_stops_on_a_signal(tmp_path, stop, started):
    proc = subprocess.Popen([*COMMAND, "--dir", str(tmp_path), "--mesh", "builtin:sphere", "--period-ms", "50"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=started)
    with reaped(proc):
        said = proc.stdout.readline()
        match = PORT_LINE.search(said)
        assert match, f"no port in {said!r}; stderr: {proc.stderr.read() if proc.poll() is not None else ''}"
        port = match.group(1)
        assert port == str(tmp_path / "ttyBRIDGE")
        record = first_record(port)
        # the backend accepted it for address 0x41; a whole record's fields came through
        assert len(record.payload) == 128 if isinstance(record, HistogramPacket) else len(record.distances_mm) == 36
        proc.send_signal(stop)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        assert "Traceback" not in err
        assert not (tmp_path / "ttyBRIDGE").exists(), "the port's link outlived the twin"
        assert out.startswith("bridge twin stopped after "), out


def test_a_bad_option_is_one_line():
    proc = subprocess.run([*COMMAND, "--period-ms", "-5"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "--period-ms" in lines[0], proc.stderr
    assert proc.stdout == ""


def test_help_says_what_the_twin_renders():
    proc = subprocess.run([*COMMAND, "--help"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    for option in ("--dir", "--mesh", "--distance-m", "--elevation-deg", "--period-ms", "--seed"):
        assert option in proc.stdout
    assert "fixed" in proc.stdout


def test_a_second_twin_on_one_folder_is_refused_and_the_first_keeps_its_port(tmp_path):
    """`--dir` made where missing; a second twin there while the first runs would take its port away."""
    rig = tmp_path / "rig"
    first = subprocess.Popen([*COMMAND, "--dir", str(rig), "--mesh", "builtin:sphere", "--period-ms", "50"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with reaped(first):
        port = PORT_LINE.search(first.stdout.readline()).group(1)
        second = subprocess.run([*COMMAND, "--dir", str(rig), "--mesh", "builtin:sphere"], capture_output=True,
                                text=True, timeout=60)
        assert second.returncode == 1 and len(second.stderr.strip().splitlines()) == 1, second.stderr
        assert "is the port of a twin still running" in second.stderr and "another --dir" in second.stderr
        assert first_record(port) is not None, "the first twin's port still leads to it"
        first.send_signal(signal.SIGINT)
        first.communicate(timeout=30)
    assert first.returncode == 0 and not (rig / "ttyBRIDGE").exists()


def test_a_signal_the_kernel_hands_to_another_thread_still_stops_the_twin():
    """The kernel may deliver Ctrl-C to any thread of the twin: handed to one of its stream's threads, it left a main
    thread that waited on an event asleep for good (the CI's full run saw it hang 30 s under load). Here a thread of
    this process takes the signal; a second one, to the main thread, after 20 s, would end the old wait only then."""
    from spadscan.daemon.sensor.sim_bridge import _serve_until_stopped

    main = threading.get_ident()
    before = signal.getsignal(signal.SIGINT)

    def send():
        while signal.getsignal(signal.SIGINT) is before:  # the twin's handler set (an event, not a guess of time)
            time.sleep(0.01)
        signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # this thread's, not the main one's
        if not stopped.wait(20):
            signal.pthread_kill(main, signal.SIGINT)

    stopped = threading.Event()
    other = threading.Thread(target=send)
    t0 = time.monotonic()
    other.start()
    try:
        _serve_until_stopped("ready")
    finally:
        stopped.set()
        other.join()
    assert time.monotonic() - t0 < 10, "the main thread slept through the signal"
