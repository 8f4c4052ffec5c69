"""Malformed inputs wherever a user can give them, through the real commands: rig configs, captures, meshes and
control-socket messages. Each is one line of error (exit 1, no traceback), and a serving process keeps serving."""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from spadscan.worker.queue import Queue

from e2e_helpers import (drop_ground_truth, one_line_error, open_fds, rig_dict, settled_fds, spadscan,
                         spadscan_argv, toml_text, wait_for)


def run_many(cases: dict[str, list], parallel: int = 4, timeout: float = 300) -> dict[str, subprocess.CompletedProcess]:
    """Run `spadscan ARGS` for every case, `parallel` at a time; {case: CompletedProcess}."""
    results, pending = {}, list(cases.items())
    running: dict[str, subprocess.Popen] = {}
    deadline = time.monotonic() + timeout
    try:
        while pending or running:
            while pending and len(running) < parallel:
                name, args = pending.pop(0)
                running[name] = subprocess.Popen(spadscan_argv(*args), stdout=subprocess.PIPE,
                                                 stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
            for name, proc in list(running.items()):
                if proc.poll() is not None:
                    out, err = proc.communicate()
                    results[name] = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
                    del running[name]
            assert time.monotonic() < deadline, f"commands did not finish: {sorted(running)}"
            time.sleep(0.02)
    finally:
        for proc in running.values():
            proc.kill()
            proc.communicate()
    return results


def check_one_line_errors(results: dict, expect: dict[str, str]) -> None:
    """Every case failed with one `spadscan: error:` line containing its expected words."""
    problems = []
    for name, r in results.items():
        try:
            line = one_line_error(r)
            assert expect[name] in line, f"expected {expect[name]!r} in {line!r}"
        except AssertionError as exc:
            problems.append(f"{name}: {exc}")
    assert not problems, "\n".join(problems)


# ---- configs ---------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_malformed_rig_configs_are_one_line_errors_before_anything_starts(tmp_path, sock_dir):
    garbage = tmp_path / "garbage.obj"
    garbage.write_bytes(b"v 1 2\nf 1 2 3\n\x00\xff")
    hand_eye_mm = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 50], [0, 0, 0, 1]]
    variants = {  # name -> (rig_dict sections, words the error must hold)
        "unknown-top-key": ({"top": {"captuers": "x"}}, "unknown key 'captuers'"),
        "unknown-key": ({"scan": {"veiws": 3}}, "[scan] unknown key 'veiws'"),
        "unknown-table": ({"sensr": {"backend": "sim"}}, "unknown table [sensr], did you mean [sensor]?"),
        "bad-value": ({"scan": {"views": 0}}, "views = 0 is outside"),
        "wrong-type": ({"arm": {"speed": "fast"}}, "speed = 'fast' must be a finite number"),
        "hand-eye-mm": ({"arm": {"hand_eye": hand_eye_mm}}, "give it in metres"),
        "missing-mesh": ({"sensor": {"mesh": str(tmp_path / "nope.obj")}}, "nope.obj: no such file"),
        "garbage-mesh": ({"sensor": {"mesh": str(garbage)}}, "garbage.obj"),
        "other-backend-key": ({"sensor": {"port": "/dev/ttyACM0"}}, "port applies only to backend 'serial'"),
        "unreachable": ({"arm": {"workspace_min": [-0.1, -0.1, 0.0], "workspace_max": [0.1, 0.1, 0.2]}},
                        "unreachable"),
        "socket-folder": ({"top": {"socket": "/nonexistent-e2e/x.sock"}}, "no such folder"),
    }
    cases, expect = {}, {}
    for name, (sections, words) in variants.items():
        data = rig_dict(tmp_path / f"caps-{name}", sock_dir / f"{name}.sock", **sections)
        (tmp_path / f"{name}.toml").write_text(toml_text(data))
        cases[name], expect[name] = ["daemon", "--config", tmp_path / f"{name}.toml"], words
    (tmp_path / "not-toml.toml").write_text('captures = "caps"\n[arm\nbackend = "sim"\n')
    (tmp_path / "binary.toml").write_bytes(b"\xff\xfe\x00\x01garbage\x80")
    for name, words in (("not-toml", "not valid TOML"), ("binary", "binary.toml"), ("missing-file", "no such")):
        cases[name], expect[name] = ["daemon", "--config", tmp_path / f"{name}.toml"], words
    results = run_many(cases)
    check_one_line_errors(results, expect)
    for name in variants:
        assert str(tmp_path / f"{name}.toml") in results[name].stderr, "the error names the file"
        assert not (tmp_path / f"caps-{name}").exists(), f"{name}: captures root created before the check failed"
    assert not list(sock_dir.iterdir()), "no socket was created"


# ---- meshes ----------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_malformed_meshes_are_one_line_errors(tmp_path):
    rng = np.random.default_rng(0)
    files = {"garbage.obj": b"garbage here\nv 1 2\nf 1 2 3\n", "noise.stl": rng.bytes(3000),
             "nan.obj": b"v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"}
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    cases = {f"simulate {name}": ["simulate", tmp_path / name, "--out", tmp_path / f"cap-{name}", "--views", 4,
                                  "--no-progress"] for name in files}
    cases["eval mesh"] = ["eval", tmp_path / "garbage.obj", "--gt", "builtin:sphere", "--points", 1000]
    cases["eval gt"] = ["eval", "builtin:sphere", "--gt", tmp_path / "noise.stl", "--points", 1000]
    expect = {name: name.split()[-1] for name in cases}
    expect.update({"eval mesh": "garbage.obj", "eval gt": "noise.stl"})
    check_one_line_errors(run_many(cases), expect)
    assert not list(tmp_path.glob("cap-*")), "no capture folder is left from a mesh that could not be read"


# ---- captures --------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def good_capture(tmp_path_factory) -> Path:
    """A small simulated capture without a ground truth, made once for the capture tests (copy it to change it)."""
    folder = tmp_path_factory.mktemp("captures") / "good"
    r = spadscan("simulate", "builtin:sphere", "--out", folder, "--views", 4, "--rays-per-zone", 16, "--sensor",
                 "tmf8820", "--no-progress")
    assert r.returncode == 0, r.stderr
    drop_ground_truth(folder)
    return folder


def corrupt(good, folder, how: str) -> None:
    shutil.copytree(good, folder)
    chunk = folder / "chunk-000000"
    if how == "hists":
        (chunk / "hists.npy").write_bytes(b"\x93NUMPY garbage")
    elif how == "meta":
        (chunk / "meta.json").write_text("{not json")
    elif how == "pose":
        poses = np.load(chunk / "poses.npy")
        poses[0, 0, 3] = np.nan
        np.save(chunk / "poses.npy", poses)
    elif how == "manifest":
        (folder / "scan.json").write_bytes(b"\x00\xff binary")
    else:
        raise ValueError(how)


@pytest.mark.slow
def test_corrupt_captures_are_one_line_errors_in_reconstruct(tmp_path, good_capture):
    cases, expect = {}, {}
    for how, words in (("hists", "hists.npy"), ("pose", "pose"), ("manifest", "scan.json")):
        corrupt(good_capture, tmp_path / how, how)
        cases[how] = ["reconstruct", tmp_path / how, "--out", tmp_path / f"out-{how}", "--steps", 2, "--device",
                      "cpu", "--no-progress"]
        expect[how] = words
    check_one_line_errors(run_many(cases, parallel=3), expect)


@pytest.mark.slow
def test_worker_fails_a_corrupt_capture_in_one_line_and_keeps_serving(tmp_path, procs, good_capture):
    root = tmp_path / "captures"
    root.mkdir()
    corrupt(good_capture, root / "bad", "meta")
    worker = procs.start(spadscan_argv("worker", "--root", root, "--steps", 2, "--device", "cpu", "--poll-s", 0.2),
                         "worker")

    def states():  # read in this process: a `--status` process every poll would load the machine
        return {row.id: row.state for row in Queue.for_root(root, create=False).statuses()}

    wait_for(lambda: states() == {"bad-fast": "failed"}, "the bad job to fail", 120, poll_s=0.2)
    shutil.copytree(good_capture, root / "later")  # a scan that arrives afterwards is still served
    wait_for(lambda: states().get("later-fast") == "done", "the later scan reconstructed", 240, poll_s=0.2)
    assert worker.poll() is None, "the worker is still serving"
    r = spadscan("worker", "--root", root, "--status", "--json")
    assert r.returncode == 0, r.stderr
    rows = {row["id"]: row for row in json.loads(r.stdout)}
    bad = rows["bad-fast"]
    assert bad["attempts"] == 1, "a bad input is not retried"
    assert "meta.json" in bad["error"] and "\n" not in bad["error"] and "Traceback" not in bad["error"]
    log = procs.log(worker)
    assert "Traceback" not in log
    assert [line for line in log.splitlines() if "bad-fast failed" in line and "meta.json" in line]
    assert procs.stop(worker) == 0, procs.log(worker)


# ---- control messages ------------------------------------------------------------------------------------------------
NL = b"\n"


def exchange(path, payload: bytes, replies: int = 1, timeout_s: float = 60.0) -> list[dict]:
    """Send raw bytes on a fresh connection; read `replies` reply lines (each must be JSON)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout_s)
        s.connect(str(path))
        s.sendall(payload)
        buf = b""
        while buf.count(b"\n") < replies:
            data = s.recv(65536)
            assert data, f"connection closed after {buf.count(NL)} of {replies} replies"
            buf += data
    return [json.loads(line) for line in buf.splitlines()]


def hang_up(path, payload: bytes) -> None:
    """Connect, send `payload` (maybe half a line), and go away without reading."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.connect(str(path))
        if payload:
            s.sendall(payload)


BAD_LINES = {
    b"{not json\n": "malformed JSON",
    b'{"op": "frobnicate"}\n': "unknown op",
    b"[1, 2, 3]\n": "JSON object",
    b'"status"\n': "JSON object",
    b'{"op": 5}\n': "string 'op'",
    b'{"op": "status", "extra": 1}\n': "takes no extra",
    b'{"op": "scan", "options": "views=3"}\n': "options must be a JSON object",
    b'{"op": "scan", "options": {"views": -1}}\n': "views",
    b'{"op": "scan", "options": {"bogus": 1}}\n': "unknown key 'bogus'",
    b'{"op": "wait", "name": 5}\n': "name",
    b'{"op": "resume"}\n': "nothing to resume",
    b"\xff\xfe\xfd\n": "not UTF-8",
    b'{"op": "status"}\x00\n': "NUL",
    b"\n": "empty request",
    b'{"op": "status", "op": "shutdown"\n': "malformed JSON",
    b"1e999999\n": "JSON object",
}


def test_malformed_control_messages_get_one_line_errors_and_the_daemon_keeps_serving(make_daemon):
    daemon = make_daemon().start()
    sock = daemon.sock
    fds_before = len(open_fds(daemon.pid))
    for line, words in BAD_LINES.items():
        (reply,) = exchange(sock, line)
        assert reply["ok"] is False and words in reply["error"] and "\n" not in reply["error"], (line, reply)
        assert "internal error" not in reply["error"], reply
    # All of them on one connection, then a good request: the connection keeps serving.
    replies = exchange(sock, b"".join(BAD_LINES) + b'{"op": "status"}\n', replies=len(BAD_LINES) + 1)
    assert [r["ok"] for r in replies] == [False] * len(BAD_LINES) + [True]
    # An oversized line (10 MB, then its newline), and binary garbage, then status on the same connection.
    big, status = b"x" * (10 * 1024 * 1024) + b"\n", b'{"op": "status"}\n'
    over, after = exchange(sock, big + status, replies=2)
    assert over["ok"] is False and "longer than" in over["error"] and after["ok"] is True
    noise = bytes(b for b in np.random.default_rng(1).bytes(100_000) if b != 10)
    replies = exchange(sock, noise + b"\n" + status, replies=2)
    assert replies[0]["ok"] is False and replies[1]["ok"] is True
    # Clients that hang up: before sending, mid-line, mid-oversized-line, before reading the reply.
    for payload in (b"", b'{"op": "sta', b"y" * (3 * 1024 * 1024), status, status * 50):
        hang_up(sock, payload)
    # A client that connects and says nothing does not block the others.
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as idle:
        idle.connect(str(sock))
        assert daemon.status()["state"] == "idle"
    assert daemon.proc.poll() is None
    s = daemon.status()
    assert s["state"] == "idle" and s["daemon"]["pid"] == daemon.pid
    wait_for(lambda: len(open_fds(daemon.pid)) <= fds_before, "the daemon to close every client connection", 30)
    assert "Traceback" not in daemon.log()
    assert daemon.stop() == 0, daemon.log()


@pytest.mark.slow
def test_clients_that_hang_up_on_wait_release_their_connections(make_daemon):
    # A scan paused by a protective stop that nobody resumes: `wait` on it does not return.
    daemon = make_daemon(arm={"protective_stop_on_move": [2]}, scan={"views": 4}).start()
    daemon.call("scan", name="held")
    daemon.wait_state("paused")
    before = len(settled_fds(daemon.pid))
    for _ in range(20):
        hang_up(daemon.sock, b'{"op": "wait", "name": "held"}\n')
    assert daemon.status()["state"] == "paused"
    wait_for(lambda: len(open_fds(daemon.pid)) <= before, "the abandoned wait connections to be closed", 60)
    assert daemon.stop() == 0, daemon.log()
