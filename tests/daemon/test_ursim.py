"""The simulated UR controller, spoken to with raw sockets: RTDE packages, recipes, streaming, the control-script
register protocol, the dashboard, the script port, faults, and clean shutdown."""

from __future__ import annotations

import itertools
import math
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from spadscan.daemon.ursim import SimURController
from spadscan.daemon.ursim import rtde_codec as codec
from spadscan.daemon.ursim.kinematics import forward_kinematics, inverse_kinematics, profile_duration
from spadscan.daemon.ursim.script_port import take_programs
from spadscan.protocol.errors import DeviceError

_hosts = itertools.count(1)
STATE = ["timestamp", "actual_TCP_pose", "actual_q", "runtime_state", "output_int_register_0",
         "output_int_register_2", "safety_mode", "safety_status_bits", "robot_status_bits", "input_int_register_0"]
CMD = ["input_int_register_0", "input_int_register_1"] + [f"input_double_register_{i}" for i in range(8)]
PROGRAM = b"def rtde_control():\n    textmsg(\"hi\")\n    while True:\n        sync()\n    end\nend\n"


@pytest.fixture
def sim():
    """A controller on a fresh loopback address (127.78.P.N), stopped after the test."""
    for _ in range(10):
        host = f"127.78.{os.getpid() % 250}.{next(_hosts) % 250 + 1}"
        try:
            controller = SimURController(host, time_scale=0.0).start()
            break
        except DeviceError:  # address in use by another run: take the next one
            continue
    else:
        raise AssertionError("no free loopback address for the simulated controller")
    yield controller
    controller.stop()


class Client:
    """A minimal RTDE client over one socket."""

    def __init__(self, host: str, port: int = 30004):
        self.sock = socket.create_connection((host, port), timeout=10)
        self.buffer = bytearray()

    def send(self, kind: str, payload: bytes = b"") -> None:
        self.sock.sendall(codec.pack(ord(kind), payload))

    def receive(self, kind: str | None = None) -> tuple[str, bytes]:
        """The next package (of `kind`, skipping others)."""
        while True:
            for k, payload in codec.split(self.buffer):
                if kind is None or chr(k) == kind:
                    return chr(k), payload
            data = self.sock.recv(65536)
            assert data, "server closed the connection"
            self.buffer += data

    def request(self, kind: str, payload: bytes = b"") -> bytes:
        self.send(kind, payload)
        return self.receive(kind)[1]

    def outputs(self, names: list[str], freq: float = 100.0) -> tuple[int, list[str]]:
        reply = self.request("O", struct.pack(">d", freq) + ",".join(names).encode())
        return reply[0], reply[1:].decode().split(",")

    def inputs(self, names: list[str]) -> tuple[int, list[str]]:
        reply = self.request("I", (",".join(names) + ",").encode())  # trailing comma, as ur_rtde sends it
        return reply[0], reply[1:].decode().split(",")

    def data(self, types: list[str]) -> dict:
        _, payload = self.receive("U")
        return dict(zip(STATE, codec.decode_values(types, payload[1:])))

    def close(self) -> None:
        self.sock.close()


def wait_until(predicate, what: str, timeout_s: float = 20.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.005)
    raise AssertionError(f"timed out waiting for {what}")


def streaming_client(sim) -> tuple[Client, list[str]]:
    c = Client(sim.host)
    rid, types = c.outputs(STATE)
    assert rid == 1
    assert c.request("S") == b"\x01"
    return c, types


def send_program(host: str) -> None:
    with socket.create_connection((host, 30003), timeout=10) as s:
        s.sendall(PROGRAM)
        time.sleep(0.05)


def command(c: Client, rid: int, cmd: int, regs=(0.0,) * 8, asynchronous: int = 0) -> None:
    types = ["INT32", "INT32"] + ["DOUBLE"] * 8
    c.send("U", bytes([rid]) + codec.encode_values(types, [cmd, asynchronous, *regs]))


def test_codec_round_trips_every_type_and_splits_partial_packages():
    types = list(codec.TYPE_FORMATS)
    values = [True, 7, 2**32 - 1, 2**64 - 1, -5, 1.5, (1.0, 2.0, 3.0), tuple(np.arange(6.0)), (-1, 2, -3, 4, -5, 6),
              (1, 2, 3, 4, 5, 6)]
    assert codec.decode_values(types, codec.encode_values(types, values)) == values
    stream = bytearray(codec.pack(ord("U"), b"\x01abc") + codec.pack(ord("S")))
    tail = bytearray(stream[-2:])
    head = bytearray(stream[:-2])
    assert codec.split(head) == [(ord("U"), b"\x01abc")]
    head += tail
    assert codec.split(head) == [(ord("S"), b"")] and not head


def test_handshake_version_and_recipe_ids(sim):
    c = Client(sim.host)
    assert c.request("V", struct.pack(">H", 2)) == b"\x01"
    assert c.request("V", struct.pack(">H", 3)) == b"\x00"
    assert struct.unpack(">IIII", c.request("v")) == (5, 15, 0, 0)
    assert c.outputs(["timestamp", "actual_q"]) == (1, ["DOUBLE", "VECTOR6D"])
    assert c.outputs(["no_such_variable", "timestamp"]) == (0, ["NOT_FOUND", "DOUBLE"])
    assert c.outputs(["runtime_state"]) == (2, ["UINT32"])
    assert c.inputs(["input_int_register_0"]) == (1, ["INT32"])
    assert c.inputs(["input_int_register_0", "input_double_register_3"]) == (2, ["INT32", "DOUBLE"])
    assert c.inputs(["input_int_register_0", "bogus"]) == (0, ["INT32", "NOT_FOUND"])
    assert c.inputs(["external_force_torque"]) == (3, ["VECTOR6D"])
    other = Client(sim.host)
    assert other.inputs(["input_int_register_0"]) == (0, ["IN_USE"])
    c.close()
    wait_until(lambda: other.inputs(["input_int_register_0"])[0] == 1, "the register to be released")
    other.close()


def test_streams_advancing_timestamps_until_paused(sim):
    c, types = streaming_client(sim)
    first = [c.data(types) for _ in range(5)]
    stamps = [d["timestamp"] for d in first]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert np.allclose(first[0]["actual_TCP_pose"], (0.3, 0.0, 0.3, 0.0, math.pi, 0.0))
    assert np.allclose(first[0]["actual_q"], inverse_kinematics(np.array(first[0]["actual_TCP_pose"])))
    assert first[0]["runtime_state"] == 1 and first[0]["safety_mode"] == 1 and first[0]["safety_status_bits"] == 1
    c.send("P")
    c.receive("P")
    c.sock.settimeout(0.3)
    c.buffer.clear()
    with pytest.raises(TimeoutError):
        c.sock.recv(65536)
    c.close()


def test_script_then_move_command_register_protocol(sim):
    c, types = streaming_client(sim)
    rid, _ = c.inputs(CMD)
    send_program(sim.host)
    wait_until(lambda: (d := c.data(types))["runtime_state"] == 2 and d["output_int_register_0"] == 1, "ready")
    assert wait_until(lambda: c.data(types)["robot_status_bits"] & 2, "program running bit")
    target = (0.4, -0.1, 0.2, 0.0, 3.0, 0.2)
    command(c, rid, 3, (*target, 0.25, 1.2))
    wait_until(lambda: c.data(types)["output_int_register_0"] == 2, "done")
    d = c.data(types)
    assert np.allclose(d["actual_TCP_pose"], target)
    command(c, rid, 0)
    wait_until(lambda: c.data(types)["output_int_register_0"] == 1, "ready again")
    command(c, rid, 1, (*inverse_kinematics(np.array([0.3, 0.1, 0.3, 0, 3.1, 0])), 1.0, 1.0), asynchronous=1)
    wait_until(lambda: c.data(types)["output_int_register_0"] == 2, "async moveJ accepted")
    wait_until(lambda: not c.data(types)["output_int_register_2"] & 32768, "async move finished")
    assert np.allclose(c.data(types)["actual_TCP_pose"], [0.3, 0.1, 0.3, 0, 3.1, 0])
    moves = sim.moves
    assert [m.name for m in moves] == ["moveL", "moveJ"]
    assert moves[0].target == target and (moves[0].speed, moves[0].accel) == (0.25, 1.2)
    assert moves[1].asynchronous and not moves[0].asynchronous
    command(c, rid, 0)
    command(c, rid, 255)
    wait_until(lambda: c.data(types)["runtime_state"] == 1, "script stopped")
    c.close()


def test_motion_takes_scaled_time_and_interpolates():
    assert profile_duration(0.0, 0.1, 1.0) == 0.0
    assert math.isclose(profile_duration(1.0, 0.5, 1.0), 2.5)  # cruise 2 s + ramps 0.5 s
    assert math.isclose(profile_duration(0.01, 1.0, 1.0), 0.2)  # triangular: 2 sqrt(d / a)
    q = np.array([0.1, -1.0, 1.2, -0.4, -1.5, 0.3])
    assert np.allclose(inverse_kinematics(forward_kinematics(q)), q)


def test_protective_stop_pauses_the_program_until_the_script_is_uploaded_again(sim):
    """A protective stop pauses the program (runtime_state 4): it takes no command during the stop nor after it is
    cleared; the next upload (ur_rtde's reuploadScript) starts a program that takes them."""
    c, types = streaming_client(sim)
    rid, _ = c.inputs(CMD)
    send_program(sim.host)
    wait_until(lambda: c.data(types)["output_int_register_0"] == 1, "ready")
    sim.protective_stop()
    d = wait_until(lambda: (d := c.data(types))["safety_mode"] == 3 and d, "protective stop")
    assert d["safety_status_bits"] & 4 and d["runtime_state"] == 4 and not d["robot_status_bits"] & 2
    command(c, rid, 3, (0.5, 0.0, 0.3, 0.0, 3.0, 0.0, 0.25, 1.2))
    for _ in range(5):
        assert c.data(types)["output_int_register_0"] != 2
    sim.clear_protective_stop()
    d = wait_until(lambda: (d := c.data(types))["safety_mode"] == 1 and d, "normal mode")
    assert not d["safety_status_bits"] & 4 and d["runtime_state"] == 4
    for _ in range(5):
        assert c.data(types)["output_int_register_0"] != 2
    assert sim.moves == []
    command(c, rid, 0)
    wait_until(lambda: c.data(types)["input_int_register_0"] == 0, "the cleared command to arrive")
    send_program(sim.host)
    wait_until(lambda: (d := c.data(types))["runtime_state"] == 2 and d["output_int_register_0"] == 1, "ready")
    command(c, rid, 3, (0.5, 0.0, 0.3, 0.0, 3.0, 0.0, 0.25, 1.2))
    wait_until(lambda: c.data(types)["output_int_register_0"] == 2, "done after the upload")
    assert len(sim.moves) == 1
    c.close()


def test_bad_move_is_a_script_error(sim):
    c, types = streaming_client(sim)
    rid, _ = c.inputs(CMD)
    send_program(sim.host)
    wait_until(lambda: c.data(types)["output_int_register_0"] == 1, "ready")
    command(c, rid, 3, (math.nan, 0.0, 0.3, 0.0, 3.0, 0.0, 0.25, 1.2))
    wait_until(lambda: c.data(types)["runtime_state"] == 1, "the script to stop")
    assert sim.moves == [] and len(sim.model.errors) == 1
    assert np.all(np.isfinite(c.data(types)["actual_TCP_pose"]))
    c.close()


def test_dashboard_answers_what_ur_rtde_asks(sim):
    with socket.create_connection((sim.host, 29999), timeout=10) as s:
        f = s.makefile("rwb")
        assert f.readline().startswith(b"Connected: Universal Robots Dashboard Server")
        replies = {}
        for cmd in ("PolyscopeVersion", "get serial number", "is in remote control", "safetystatus", "bogus"):
            f.write(cmd.encode() + b"\n")
            f.flush()
            replies[cmd] = f.readline().decode().strip()
    assert replies["PolyscopeVersion"].startswith("URSoftware 5.15")
    assert replies["get serial number"].isdigit()
    assert replies["is in remote control"] == "true"
    assert replies["safetystatus"] == "Safetystatus: NORMAL"
    assert replies["bogus"] == "could not understand: 'bogus'"
    assert sim.dashboard_log[:2] == ["PolyscopeVersion", "get serial number"]


def test_script_port_splits_programs():
    buf = bytearray(PROGRAM + PROGRAM[:20])
    assert take_programs(buf) == [PROGRAM.decode().strip()]
    assert bytes(buf) == PROGRAM[:20]


@pytest.mark.parametrize("mode", ["close", "silent", "freeze"])
def test_link_faults(sim, mode):
    c, types = streaming_client(sim)
    c.data(types)
    sim.drop_link(mode)
    if mode == "close":
        c.sock.settimeout(5)
        with pytest.raises(AssertionError, match="closed"):
            while True:
                c.data(types)
    elif mode == "silent":
        c.sock.settimeout(0.3)
        c.buffer.clear()
        with pytest.raises(TimeoutError):
            while True:
                c.data(types)
    else:
        stamps = {c.data(types)["timestamp"] for _ in range(5)}
        stamps = {c.data(types)["timestamp"] for _ in range(5)}
        assert len(stamps) == 1
    if mode != "freeze":
        with pytest.raises(OSError):
            socket.create_connection((sim.host, 30004), timeout=5)
    sim.restore_link()
    c2, types = streaming_client(sim)
    a, b = c2.data(types)["timestamp"], c2.data(types)["timestamp"]
    assert b > a
    c.close()
    c2.close()


def test_stop_closes_everything():
    threads = threading.active_count()
    sim = SimURController(f"127.78.{os.getpid() % 250}.251").start()
    c, _ = streaming_client(sim)
    assert sim.open_connections() == 1
    sim.stop()
    sim.stop()
    assert threading.active_count() == threads
    c.sock.settimeout(5)
    with pytest.raises(AssertionError, match="closed"):
        while True:
            c.receive()
    c.close()


def test_a_taken_address_is_one_error():
    threads = threading.active_count()
    host = f"127.78.{os.getpid() % 250}.253"
    with SimURController(host):
        with pytest.raises(DeviceError, match=host):
            SimURController(host).start()
    assert threading.active_count() == threads


def test_runs_as_a_process_and_stops_on_sigterm():
    host = f"127.78.{os.getpid() % 250}.252"
    proc = subprocess.Popen([sys.executable, "-m", "spadscan.daemon.ursim", "--host", host],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().startswith("ursim listening")
        c = Client(host)
        assert c.request("V", struct.pack(">H", 2)) == b"\x01"
        c.close()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        proc.stdout.close()


class ClockedModel:
    """The controller model on a clock the test sets (controller seconds), with the control script running."""

    def __init__(self, **kw):
        from spadscan.daemon.ursim.controller import URControllerModel

        self.t = 0.0
        self.model = URControllerModel(**kw)
        self.model.now = lambda: self.t
        self.model.start_script("def rtde_control():\nend")

    def command(self, cmd: int, regs=(0.0,) * 8, asynchronous: int = 0) -> None:
        self.model.write_inputs({"input_int_register_0": cmd, "input_int_register_1": asynchronous,
                                 **{f"input_double_register_{i}": v for i, v in enumerate(regs)}})
        self.model.write_inputs({"input_int_register_0": 0})  # the client clears the command

    def read(self, *names):
        return self.model.read(list(names))


def test_model_watchdog_stops_the_program_when_the_command_register_goes_unwritten():
    """ur_rtde's setWatchdog (command 35): rtde_set_watchdog("input_int_register_0", f, "stop"). A kick (a write of
    that register) within every 1/f s keeps the program; a longer gap stops it and halts the arm."""
    c = ClockedModel()
    c.command(35, (2.0,) + (0.0,) * 7)  # 2 Hz: 0.5 s
    assert c.model.watchdog_period_s == 0.5
    c.command(3, (0.5, 0.0, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0), asynchronous=1)  # a 2 s move
    for c.t in (0.4, 0.8, 1.2):
        c.model.check_watchdog()
        c.model.write_inputs({"input_int_register_0": 0})  # kickWatchdog
    assert c.read("runtime_state") == [2]
    c.t = 1.6
    c.model.check_watchdog()
    assert c.read("runtime_state") == [2]  # 0.4 s since the last kick
    c.t = 1.75
    c.model.check_watchdog()
    halted = c.read("actual_TCP_pose")[0]
    c.t = 3.0
    assert c.read("runtime_state", "actual_TCP_pose") == [1, halted] and halted[0] < 0.5
    assert c.model.watchdog_stops == 1 and "RTDE watchdog" in c.model.errors[-1]


def test_model_the_stop_command_ends_the_program_and_its_watchdog_as_the_control_script_does():
    """ur_rtde's stopScript writes 255: the script's main loop ends without signalling done, the program stops (the
    arm halts, a move thread writes nothing) and its watchdog goes with it: no watchdog stop follows, however long
    nothing is written. While a safety stop holds the script, the command is not taken (ur_rtde clears it again)."""
    c = ClockedModel()
    c.command(35, (2.0,) + (0.0,) * 7)  # watchdog 2 Hz
    c.model.set_safeguard_stop(True)
    c.command(255)
    assert c.read("runtime_state") == [2] and c.model.script_stops == 0
    c.model.set_safeguard_stop(False)
    c.command(3, (0.5, 0.0, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0), asynchronous=1)  # a 2 s move
    c.t = 0.2
    progress = c.read("output_int_register_2")[0]
    c.model.write_inputs({"input_int_register_0": 255})
    halted = c.read("actual_TCP_pose")[0]
    assert c.read("runtime_state", "output_int_register_0", "output_int_register_2") == [1, 1, progress]
    assert progress & RUNNING and 0.3 < halted[0] < 0.5
    assert c.model.script_stops == 1 and c.model.watchdog_period_s is None
    c.t = 5.0
    c.model.check_watchdog()
    assert c.read("runtime_state", "actual_TCP_pose") == [1, halted] and c.model.watchdog_stops == 0
    assert [m.name for m in c.model.moves] == ["moveL"]  # the stop is no move


def test_model_speed_slider_stretches_a_move_and_its_speed():
    fast, slow = ClockedModel(), ClockedModel()
    slow.model.set_speed_slider(0.25)
    goal = (0.5, 0.0, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0)
    for c in (fast, slow):
        c.command(3, goal, asynchronous=1)
    duration = profile_duration(0.2, 0.1, 1.0)
    for c in (fast, slow):
        c.t = 0.5 * duration
    assert fast.read("actual_TCP_pose")[0][0] == pytest.approx(0.4)
    (x, *_), speed, fraction = slow.read("actual_TCP_pose", "actual_TCP_speed", "target_speed_fraction")
    assert 0.3 < x < 0.35 and fraction == 0.25
    fast_speed = fast.read("actual_TCP_speed")[0][0]
    slow.t = 2.0 * duration  # half of the motion time at a quarter of the rate: where the fast one was at 0.5 d
    assert slow.read("actual_TCP_pose")[0][0] == pytest.approx(0.4)
    assert slow.read("actual_TCP_speed")[0][0] == pytest.approx(0.25 * fast_speed, rel=1e-3)
    slow.t = 4.0 * duration
    assert slow.read("actual_TCP_pose")[0][0] == pytest.approx(0.5)


def test_model_pose_noise_scatters_the_reported_pose_only():
    c = ClockedModel(seed=3)
    c.model.pose_noise_m = 2e-4
    poses = np.array([c.read("actual_TCP_pose")[0] for _ in range(400)])
    assert np.std(poses[:, :3], axis=0) == pytest.approx([2e-4] * 3, rel=0.2)
    assert np.allclose(poses.mean(axis=0)[:3], (0.3, 0.0, 0.3), atol=5e-5) and np.all(poses[:, 3:] == poses[0, 3:])


@pytest.mark.parametrize("kind, mode, bits", [("protective", 3, 1 << 2), ("emergency", 7, (1 << 6) | (1 << 7))])
def test_model_a_protective_or_emergency_stop_pauses_the_program_until_the_script_is_uploaded_again(kind, mode, bits):
    """UR: such a stop only pauses the running program (runtime_state 4, PAUSED); clearing the stop leaves it paused,
    taking no command (ur_rtde's isProgramRunning: runtime_state == PLAYING); the next upload replaces it."""
    from spadscan.daemon.ursim.dashboard import reply

    c = ClockedModel()
    set_stop(c.model, kind, True)
    assert c.read("safety_mode", "safety_status_bits", "runtime_state", "robot_status_bits") == [
        mode, bits | (1 << 10), 4, 1]
    set_stop(c.model, kind, False)
    assert c.read("safety_mode", "runtime_state") == [1, 4]
    assert reply(c.model, "programstate", "URSoftware 5.15", "1") == "PAUSED <unnamed>"
    assert reply(c.model, "running", "URSoftware 5.15", "1") == "Program running: false"
    c.command(3, (0.5, 0.0, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0))
    assert c.model.moves == [] and c.read("runtime_state", "output_int_register_0") == [4, 1]
    c.model.start_script("def rtde_control():\nend")
    c.command(3, (0.5, 0.0, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0))
    assert c.read("runtime_state") == [2] and [m.name for m in c.model.moves] == ["moveL"]


def test_model_a_safeguard_stop_holds_the_program_without_pausing_it():
    c = ClockedModel()
    c.model.set_safeguard_stop(True)
    assert c.read("safety_mode", "safety_status_bits", "runtime_state") == [5, (1 << 4) | (1 << 10), 2]
    c.command(3, (0.5, 0.0, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0))
    assert c.model.moves == []
    c.model.set_safeguard_stop(False)
    c.command(3, (0.5, 0.0, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0))
    assert c.read("runtime_state") == [2] and [m.name for m in c.model.moves] == ["moveL"]


SAFETY_STOPS = {"protective": (3, "PROTECTIVE_STOP"), "safeguard": (5, "SAFEGUARD_STOP"),
                "emergency": (7, "ROBOT_EMERGENCY_STOP")}
RUNNING = 1 << 15  # output_int_register_2: an asynchronous operation is running


def set_stop(model, kind: str, on: bool) -> None:
    getattr(model, f"set_{kind}_stop")(on)


@pytest.mark.parametrize("kind", list(SAFETY_STOPS))
def test_model_a_safety_stop_halts_an_asynchronous_move_and_leaves_it_running_as_the_script_does(kind):
    """ur_rtde's control script writes "finished" into output_int_register_2 only when the move thread's movel ends
    or a command kills the thread (stopL/stopJ, the next move): a safety stop halts the arm and no script code runs,
    so the running bit stays set. A client therefore learns of the stop from the safety state, never from a move
    that looks finished."""
    c = ClockedModel()
    c.command(3, (0.5, 0.0, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0), asynchronous=1)  # a 2 s move
    c.t = 0.5
    assert c.read("output_int_register_2")[0] & RUNNING
    set_stop(c.model, kind, True)
    halted, mode, progress = c.read("actual_TCP_pose", "safety_mode", "output_int_register_2")
    c.t = 1.5
    assert c.read("actual_TCP_pose", "output_int_register_2") == [halted, progress]  # halted, still "running"
    assert 0.3 < halted[0] < 0.5 and mode == SAFETY_STOPS[kind][0] and progress & RUNNING
    set_stop(c.model, kind, False)
    c.t = 2.5
    assert c.read("actual_TCP_pose", "output_int_register_2") == [halted, progress]  # cleared: nothing resumes
    c.command(33, (10.0,) + (0.0,) * 7)  # stopL kills the thread of a program that runs: now "finished"
    if kind == "safeguard":
        assert not c.read("output_int_register_2")[0] & RUNNING
    else:  # a paused program takes no stopL; the next one's start resets the register
        assert c.read("runtime_state", "output_int_register_2") == [4, progress]
        c.model.start_script("def rtde_control():\nend")
        assert not c.read("output_int_register_2")[0] & RUNNING


def test_model_a_program_stopped_under_a_running_move_writes_nothing_and_a_new_one_resets_the_register():
    """The watchdog stops the program mid-move: no script code runs any more, so the register still says "running"
    (the client reads that the program stopped); the next program's start resets it to "finished"."""
    c = ClockedModel()
    c.command(35, (2.0,) + (0.0,) * 7)  # watchdog 2 Hz
    c.command(3, (0.5, 0.0, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0), asynchronous=1)
    c.t = 1.0  # no kick for a second
    c.model.check_watchdog()
    assert c.read("runtime_state")[0] == 1 and c.read("output_int_register_2")[0] & RUNNING
    c.model.start_script("def rtde_control():\nend")
    assert not c.read("output_int_register_2")[0] & RUNNING


def test_model_the_next_move_after_a_safety_stop_kills_the_halted_thread_and_starts_its_own():
    c = ClockedModel()
    c.command(3, (0.5, 0.0, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0), asynchronous=1)
    c.t = 0.5
    c.model.set_safeguard_stop(True)  # a stop the program runs on through
    c.model.set_safeguard_stop(False)
    before = c.read("output_int_register_2")[0]
    c.command(3, (0.3, 0.1, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0), asynchronous=1)
    killed = c.read("output_int_register_2")[0]
    assert before & RUNNING and not killed & RUNNING  # killed first, as stop_async_move does
    c.t = 0.6
    started = c.read("output_int_register_2")[0]
    assert started & RUNNING and (started >> 24) != (before >> 24)  # a new operation id
    c.t = 10.0
    assert not c.read("output_int_register_2")[0] & RUNNING
    assert c.read("actual_TCP_pose")[0][:2] == pytest.approx([0.3, 0.1])


@pytest.mark.parametrize("kind", [None, *SAFETY_STOPS])
def test_model_the_dashboard_names_the_safety_mode_rtde_reports(kind):
    """safetymode and safetystatus answer with the safety mode's name, as a real dashboard does: the same mode RTDE's
    safety_mode gives (a safeguard stop is SAFEGUARD_STOP, not NORMAL)."""
    from spadscan.daemon.ursim.controller import URControllerModel
    from spadscan.daemon.ursim.dashboard import reply

    model = URControllerModel()
    if kind is not None:
        set_stop(model, kind, True)
    mode, name = SAFETY_STOPS[kind] if kind else (1, "NORMAL")
    assert model.read(["safety_mode", "safety_status"]) == [mode, mode]
    assert reply(model, "safetystatus", "URSoftware 5.15", "1") == f"Safetystatus: {name}"
    assert reply(model, "safetymode", "URSoftware 5.15", "1") == f"Safetymode: {name}"


@pytest.mark.parametrize("mode, name", [(8, "VIOLATION"), (9, "FAULT")])
def test_model_a_safety_violation_or_fault_holds_the_arm_and_the_program_until_the_arm_is_restarted(mode, name):
    """RTDE guide: safety mode 8 violation (safety_status_bits bit 8), 9 fault (bit 9), with bit 10. The arm halts
    and the program stops (it is not paused); unlocking a protective stop does not clear it and no
    program starts, only a restart of the arm (the dashboard's `restart safety`) does. The arm comes back from it
    powered off (robot mode 3, robot_status_bits' power bit clear) and starts no program until it is powered on (5,
    its brakes on) and its brakes released (7); the program then stays stopped until the script is uploaded again."""
    from spadscan.daemon.ursim.dashboard import reply

    c = ClockedModel()
    c.command(3, (0.5, 0.0, 0.3, 0.0, math.pi, 0.0, 0.1, 1.0), asynchronous=1)  # a 2 s move
    c.t = 0.5
    c.model.set_safety_fault(mode)
    halted = c.read("actual_TCP_pose")[0]
    c.t = 1.5
    assert c.read("actual_TCP_pose", "safety_mode", "safety_status", "safety_status_bits", "runtime_state") == [
        halted, mode, mode, (1 << mode) | (1 << 10), 1]
    assert 0.3 < halted[0] < 0.5
    assert reply(c.model, "safetymode", "URSoftware 5.15", "1") == f"Safetymode: {name}"
    assert reply(c.model, "unlock protective stop", "URSoftware 5.15", "1") == "Protective stop releasing"
    c.model.start_script("def rtde_control():\nend")  # ur_rtde's reupload: recorded, not run
    assert c.read("safety_mode", "runtime_state") == [mode, 1] and len(c.model.scripts) == 2
    assert c.read("robot_mode", "robot_status_bits") == [7, 1]
    assert reply(c.model, "restart safety", "URSoftware 5.15", "1") == "Restarting safety"
    assert c.read("safety_mode", "safety_status_bits", "runtime_state", "robot_mode", "robot_status_bits") == [
        1, 1, 1, 3, 0]
    assert reply(c.model, "robotmode", "URSoftware 5.15", "1") == "Robotmode: POWER_OFF"
    for command, answer, robot_mode in (("brake release", "Brake releasing", 3), ("power on", "Powering on", 5),
                                        ("brake release", "Brake releasing", 7)):
        c.model.start_script("def rtde_control():\nend")  # not run before the arm is powered and its brakes off
        assert c.read("runtime_state") == [1]
        assert reply(c.model, command, "URSoftware 5.15", "1") == answer
        assert c.read("robot_mode") == [robot_mode]
    assert reply(c.model, "robotmode", "URSoftware 5.15", "1") == "Robotmode: RUNNING"
    c.model.start_script("def rtde_control():\nend")
    assert c.read("runtime_state") == [2]
    assert reply(c.model, "power off", "URSoftware 5.15", "1") == "Powering off"
    assert c.read("runtime_state", "robot_mode") == [1, 3]
    with pytest.raises(ValueError, match="safety mode 8 or 9"):
        c.model.set_safety_fault(3)


def test_model_answers_safety_limit_and_inverse_kinematics_queries_from_its_reach():
    c = ClockedModel()
    c.model.safety_floor_z = 0.1
    for cmd, pose, answer in ((36, (0.4, 0.0, 0.3), 1), (36, (0.4, 0.0, 0.05), 0), (60, (0.4, 0.0, 0.05), 1),
                              (60, (1.2, 0.0, 0.3), 0), (36, (0.02, 0.0, 0.6), 0)):
        c.command(cmd, (*pose, 0.0, math.pi, 0.0, 0.0, 0.0))
        assert c.read("output_int_register_1") == [answer], (cmd, pose)
    assert [q[0] for q in c.model.queries] == ["within_safety_limits"] * 2 + ["has_ik_solution"] * 2 + \
        ["within_safety_limits"]


def test_model_answers_get_tcp_offset_in_the_output_double_registers_as_the_control_script_does():
    """ur_rtde's getTCPOffset: command 40, the script writes get_tcp_offset() to output_double_register_0..5 and
    signals done; nothing is recorded as a move. The offset is the bare flange's (zero) until configured."""
    c = ClockedModel()
    regs = [f"output_double_register_{i}" for i in range(6)]
    c.model.write_inputs({"input_int_register_0": 40})
    assert c.read("output_int_register_0", *regs) == [2] + [0.0] * 6
    c.model.write_inputs({"input_int_register_0": 0})
    assert c.read("output_int_register_0") == [1]
    c.model.tcp_offset = (0.01, -0.02, 0.15, 0.1, 0.0, -0.3)
    c.command(40)
    assert c.read(*regs) == [0.01, -0.02, 0.15, 0.1, 0.0, -0.3]
    assert c.model.moves == [] and c.model.tcp_offset_reads == 2


def test_the_tcp_offset_setting_is_checked():
    controller = SimURController("127.0.0.1")  # not started: configure only sets the model
    controller.configure(tcp_offset=[0, 0, "0.1", 0, 0, 0])
    assert controller.model.tcp_offset == (0.0, 0.0, 0.1, 0.0, 0.0, 0.0)
    for bad in ((0, 0, 0.1), (0, 0, math.nan, 0, 0, 0), "pointer", None):
        with pytest.raises(DeviceError, match="tcp_offset must be six finite numbers"):
            controller.configure(tcp_offset=bad)


def test_a_malformed_package_is_answered_with_a_text_message_and_the_session_goes_on(sim):
    """A package shorter than its type says (a bare version request, an input package short of its recipe): the
    controller says so in a text message and keeps the connection, as a real one does."""
    c = Client(sim.host)
    c.send("V")
    kind, text = c.receive("M")
    assert b"malformed V package" in text
    assert c.inputs(["input_int_register_0", "input_double_register_3"]) == (1, ["INT32", "DOUBLE"])
    c.send("U", b"\x01\x00")  # recipe 1 wants 12 bytes
    assert b"malformed U package" in c.receive("M")[1]
    assert struct.unpack(">IIII", c.request("v")) == (5, 15, 0, 0)
    c.close()
