"""`spadscan ctl` against a fake daemon on a Unix socket: --timeout takes only positive finite seconds, `wait` shows
a progress bar on a terminal (and nothing extra otherwise), and a real `spadscan ctl` process imports neither numpy
nor torch."""

from __future__ import annotations

import fcntl
import io
import json
import math
import os
import pty
import re
import select
import signal
import socketserver
import struct
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path

import pytest

from spadscan.cli import main

POSES = 6


class FakeDaemon(socketserver.ThreadingUnixStreamServer):
    """Answers `status` with a scan that advances `step` poses per status request (after `paused_polls` requests
    that find it paused), and `wait` once it is done."""

    daemon_threads = True

    def __init__(self, path: str):
        self.pose, self.step, self.paused_polls = 0, 1, 0
        self.requests: list[str] = []
        self.lock = threading.Lock()
        self.closing = False
        self.errors: list[BaseException] = []
        super().__init__(path, Handler)

    def handle_error(self, request, client_address) -> None:
        """A client that went away before its reply (Ctrl-C on `wait`) is expected: keep the error for the test
        instead of printing socketserver's traceback among the test output."""
        self.errors.append(sys.exc_info()[1])

    def status(self) -> dict:
        with self.lock:
            paused = self.paused_polls > 0
            if paused:
                self.paused_polls -= 1
            else:
                self.pose = min(POSES, self.pose + self.step)
            pose = self.pose
        state = "paused" if paused else "scanning" if pose < POSES else "idle"
        return {"ok": True, "state": state, "scan": "mug", "pose": pose, "poses": POSES,
                "progress": f"{pose}/{POSES}", "reason": "sensor silent: no frame" if paused else None}


class Handler(socketserver.StreamRequestHandler):
    def handle(self) -> None:
        req = json.loads(self.rfile.readline())
        self.server.requests.append(req["op"])
        if req["op"] == "status":
            reply = self.server.status()
        elif req["op"] == "wait":
            while self.server.pose < POSES and not self.server.closing:
                time.sleep(0.01)
            ended = {k: v for k, v in self.server.status().items() if k != "ok"}  # the status as the scan ended
            reply = {"ok": True, "name": req["name"], "state": "complete", "status": ended}
        else:
            reply = {"ok": False, "error": f"unknown op {req['op']!r}"}
        self.wfile.write((json.dumps(reply) + "\n").encode())


@pytest.fixture
def fake_daemon(sock_dir):
    server = FakeDaemon(str(sock_dir / "ctl.sock"))
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.01})
    thread.start()
    yield server, str(sock_dir / "ctl.sock")
    server.closing = True  # ends a `wait` still pending
    server.shutdown()
    server.server_close()
    thread.join()


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize("value", ["-1", "0", "nan", "inf", "-inf", "soon"])
def test_timeout_must_be_positive_and_finite(value, capsys, tmp_path):
    with pytest.raises(SystemExit) as exited:
        main(["ctl", "status", "--socket", str(tmp_path / "none.sock"), f"--timeout={value}"])
    err = capsys.readouterr().err
    assert exited.value.code == 2
    assert f"{value!r} is not a positive number of seconds" in err and "Traceback" not in err


@pytest.mark.parametrize("op", ["status", "wait"])
def test_a_timeout_too_long_to_wait_is_one_line_not_a_traceback(op, capsys, tmp_path):
    """A huge --timeout (meant as 'for ever') overflowed the socket's timeout with a traceback."""
    with pytest.raises(SystemExit) as exited:
        main(["ctl", op, "--socket", str(tmp_path / "none.sock"), "--timeout=1e12"])
    err = capsys.readouterr().err
    assert exited.value.code == 2
    assert "'1e12' seconds is more than can be waited (at most 1e+09 s" in err and "Traceback" not in err, err


@pytest.mark.parametrize("where", ["before", "after"])
def test_an_empty_socket_path_is_refused(where, capsys):
    """`--socket ''` is an error, not the default socket."""
    argv = ["ctl", "--socket", "", "status"] if where == "before" else ["ctl", "status", "--socket", " "]
    with pytest.raises(SystemExit) as exited:
        main(argv)
    assert exited.value.code == 2 and "an empty path names no socket" in capsys.readouterr().err


def test_help_of_scan_and_wait(capsys):
    for op in ("scan", "wait"):
        with pytest.raises(SystemExit):
            main(["ctl", op, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "Every scan setting left out takes the daemon's default: the [scan] value of its rig config" in text
    assert "--views VIEWS number of sensor poses [views]" in text
    assert "NAME the scan's name (its folder under the captures root)" in text


def test_the_help_of_stop_when_converged_gives_the_figures_of_the_rig_docs_and_the_live_refit_rule(capsys):
    """`ctl scan --help` and examples/README.md say how slowly poses must come for a scan to end early, and both
    follow the live job's rule: each refit (every min(rebuild_views, a rebuild_growth share of the views) views)
    starts the ~100 s plateau test again, so the pose interval needed scales as 1 / that spacing."""
    with pytest.raises(SystemExit):
        main(["ctl", "scan", "--help"])
    helped = " ".join(capsys.readouterr().out.split())
    documented = " ".join((Path(__file__).parents[2] / "examples" / "README.md").read_text().split())
    figures = re.compile(r"a pose every ([\d.]+) s or more with (\d+) views in, ([\d.]+) s or more past (\d+)")
    said, doc = figures.search(helped), figures.search(documented)
    assert said is not None, helped
    assert doc is not None and said.groups() == doc.groups()
    slow_s, few, fast_s, many = float(said[1]), int(said[2]), float(said[3]), int(said[4])
    from spadscan.worker.live.job import LiveSettings  # here: it brings torch, which the other tests here do without

    live = LiveSettings()

    def spacing(views: int) -> int:  # views between two refits (worker/live/job.py refit_due)
        return max(1, min(live.rebuild_views, math.ceil(live.rebuild_growth * views)))

    assert spacing(many) == live.rebuild_views  # past `many` views the spacing no longer grows
    assert slow_s * spacing(few) == pytest.approx(fast_s * spacing(many), rel=0.05)


def test_wait_on_a_terminal_shows_pose_progress(fake_daemon, monkeypatch, capsys):
    server, path = fake_daemon
    terminal = Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    monkeypatch.setattr("spadscan.commands.ctl.PROGRESS_POLL_S", 0.01)
    assert main(["ctl", "--socket", path, "wait", "mug"]) == 0
    shown = terminal.getvalue()
    assert "mug" in shown and f"{POSES}/{POSES}" in shown and "complete" in shown
    assert any(f"{i}/{POSES}" in shown for i in range(1, POSES))  # it moved on the way
    assert json.loads(capsys.readouterr().out) == {"name": "mug", "state": "complete"}
    assert "status" in server.requests


def test_wait_without_a_terminal_prints_only_the_result(fake_daemon, capsys):
    server, path = fake_daemon
    server.pose = POSES
    assert main(["ctl", "--socket", path, "wait", "mug"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == {"name": "mug", "state": "complete"} and err == ""
    assert server.requests == ["wait"]


def test_wait_without_a_terminal_says_once_why_the_scan_paused(fake_daemon, monkeypatch, capsys):
    server, path = fake_daemon
    server.pose, server.paused_polls = 2, 5
    monkeypatch.setattr("spadscan.commands.ctl.PROGRESS_POLL_S", 0.01)
    assert main(["ctl", "--socket", path, "--timeout", "120", "wait", "mug"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == {"name": "mug", "state": "complete"}
    assert err == "spadscan: scan 'mug' paused at pose 2/6: sensor silent: no frame (`spadscan ctl resume` " \
                  "continues it)\n", err


def test_wait_that_runs_out_of_time_says_how_far_the_scan_got(fake_daemon, monkeypatch, capsys):
    server, path = fake_daemon
    server.pose, server.step = 3, 0  # a healthy scan that is not done in time
    monkeypatch.setattr("spadscan.commands.ctl.PROGRESS_POLL_S", 0.01)
    assert main(["ctl", "--socket", path, "--timeout", "0.2", "wait", "mug"]) == 1
    out, err = capsys.readouterr()
    assert out == "" and err == "spadscan: error: scan 'mug' still scanning at pose 3/6 after 0.2 s\n", err


def interrupted_wait(server, path: str, *flags: str) -> tuple[int, str, str]:
    """`ctl wait mug` (with `flags`) as a real process, sent Ctrl-C once the fake daemon has its `wait` request:
    (exit status, stdout, stderr)."""
    server.step = 0
    proc = subprocess.Popen([sys.executable, "-m", "spadscan.cli", "ctl", "--socket", path, "wait", "mug", *flags],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while "wait" not in server.requests:
            assert proc.poll() is None and time.monotonic() < deadline, "the client never sent its wait request"
            time.sleep(0.01)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, out, err


def test_ctrl_c_during_wait_says_the_scan_goes_on(fake_daemon):
    """The interrupt comes once the daemon has the `wait` request (the client is then blocked in it), however long a
    loaded machine takes to start the client; the fake daemon's handler, left writing to a closed connection, keeps
    its error to itself."""
    code, out, err = interrupted_wait(*fake_daemon)
    assert code == 130 and out == ""
    assert err == "spadscan: interrupted; scan 'mug' goes on in the daemon (`spadscan ctl wait mug` waits again, " \
                  "`spadscan ctl abort` stops it)\n", err


def imported(importtime_output: str) -> set[str]:
    """Top-level package names from `python -X importtime` lines ('import time: self | cumulative | name')."""
    names = set()
    for line in importtime_output.splitlines():
        if line.startswith("import time:") and line.count("|") == 2:
            names.add(line.rsplit("|", 1)[1].strip().split(".")[0])
    return names


CTL = [sys.executable, "-X", "importtime", "-c", "import sys; from spadscan.cli import main; sys.exit(main())"]


def test_ctl_status_process_imports_neither_numpy_nor_torch(fake_daemon):
    _, path = fake_daemon
    r = subprocess.run(CTL + ["ctl", "--socket", path, "status"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["scan"] == "mug"
    names = imported(r.stderr)
    assert "spadscan" in names and "json" in names  # the listing is real
    assert not names & {"numpy", "torch", "trimesh", "tqdm"}, sorted(names)


def test_ctl_wait_on_a_terminal_imports_tqdm_but_not_numpy(fake_daemon):
    """stderr on a pseudo-terminal: the progress bar appears, tqdm is imported, numpy and torch still are not."""
    server, path = fake_daemon
    server.step = 3  # done after two polls
    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))  # 24 rows, 100 columns
    proc = subprocess.Popen(CTL + ["ctl", "--socket", path, "wait", "mug"], stdout=subprocess.PIPE,
                            stderr=follower, text=True)
    os.close(follower)
    chunks = []
    try:
        while True:
            ready, _, _ = select.select([leader], [], [], 60)
            assert ready, "ctl wait printed nothing for 60 s"
            try:
                data = os.read(leader, 65536)
            except OSError:  # the process closed its end
                break
            if not data:
                break
            chunks.append(data.decode(errors="replace"))
        out = proc.stdout.read()
        assert proc.wait(60) == 0
    finally:
        proc.stdout.close()
        os.close(leader)
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    shown = "".join(chunks)
    assert "mug: 100%" in shown or f"{POSES}/{POSES}" in shown, shown[-2000:]
    assert json.loads(out) == {"name": "mug", "state": "complete"}
    names = imported(shown)
    assert "tqdm" in names and not names & {"numpy", "torch"}, sorted(names)


def test_ctl_in_a_login_shell_finds_the_default_socket_of_a_daemon_run_by_systemd(tmp_path, sock_dir, monkeypatch,
                                                                                 capsys):
    """The shipped unit runs the daemon without XDG_RUNTIME_DIR (systemd sets no session variables); the same user's
    login shell has it. With `socket` left at its default, as in every example config, `spadscan ctl status` from
    that shell reaches the daemon. (The default folder is made in the test's short sock_dir, not /tmp.)"""
    import spadscan.daemon.client as client
    from spadscan.daemon.config import config_from_dict

    monkeypatch.setattr(client, "SOCKET_ROOT", str(sock_dir))
    monkeypatch.delenv("SPADSCAN_SOCKET", raising=False)
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)  # the service's environment
    cfg = config_from_dict({"captures": str(tmp_path), "sensor": {"backend": "sim", "mesh": "builtin:sphere"}},
                           tmp_path / "rig.toml")
    server = FakeDaemon(str(cfg.socket))
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.01})
    thread.start()
    try:
        (tmp_path / "run-user").mkdir(mode=0o700)
        monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "run-user"))  # the login shell's
        assert main(["ctl", "status"]) == 0, capsys.readouterr().err
    finally:
        server.shutdown()
        server.server_close()
        thread.join()
    assert json.loads(capsys.readouterr().out)["scan"] == "mug" and server.requests == ["status"]


@pytest.mark.parametrize("argv, waits", [(["scan"], 600.0), (["resume"], 600.0), (["status"], 30.0),
                                         (["--timeout", "5", "scan"], 5.0)])
def test_scan_and_resume_wait_longer_for_their_reply(tmp_path, monkeypatch, capsys, argv, waits):
    """Before the arm moves the daemon asks the arm's controller about every pose left (minutes for thousands):
    `scan` and `resume` wait 600 s for their reply unless told, the rest 30 s."""
    import spadscan.daemon.client as client

    asked = []
    monkeypatch.setattr(client, "call", lambda path, op, timeout, **request: asked.append(timeout) or
                        {"ok": True, "scan": "s"})
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), *argv]) == 0
    assert asked == [waits]


SCANNING = {"ok": True, "state": "scanning", "scan": "mug", "last_error": None, "arm": "arm (sim)",
            "sensor": {"name": "sensor sim", "frames": 0, "silent": False, "link": "up"},
            "path": "/caps/mug", "pose": 0, "poses": 128, "progress": "0/128", "frames": 0, "reason": None,
            "daemon_stalls": {"stalls": 0}}
"""The start of the daemon's reply to `scan` (its whole status, a dozen keys more in a real one)."""


@pytest.mark.parametrize("argv, reply, said", [
    (["scan", "--name", "mug"], SCANNING, "scan 'mug' scanning at pose 0/128; written to /caps/mug"),
    (["pause"], {**SCANNING, "state": "pausing", "pose": 3, "progress": "3/128", "pausing_at": "4/128"},
     "scan 'mug' pausing at pose 3/128 (it stops at pose 4/128, once the poses under way are published)"),
    (["resume"], {**SCANNING, "state": "paused", "progress": "4/128", "reason": "sensor silent"},
     "scan 'mug' paused at pose 4/128: sensor silent"),
    (["resume"], {**SCANNING, "progress": "40/128", "poses_to_take_again": [12, 13]},
     "scan 'mug' scanning at pose 40/128; taking pose(s) 12, 13 again first"),
    (["abort"], {**SCANNING, "state": "idle", "scan": None, "aborted": "mug", "abort_recorded": True},
     "scan 'mug' aborted at pose 0/128"),  # (the pose it stopped at: `progress`)
    (["shutdown"], {"ok": True, "stopping": True}, "the daemon is stopping (a scan in flight stays resumable)"),
])
def test_ops_that_change_the_daemon_answer_in_one_line_for_people_and_in_json_with_json(
        tmp_path, monkeypatch, capsys, argv, reply, said):
    """`ctl scan` and `ctl pause` printed the daemon's whole status as one line of raw JSON (about 600 characters):
    they, `resume`, `abort` and `shutdown` now say the scan, its state and its pose i/n; --json keeps the reply."""
    import spadscan.daemon.client as client

    monkeypatch.setattr(client, "call", lambda path, op, timeout, **request: dict(reply))
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), *argv]) == 0
    assert capsys.readouterr().out == said + "\n"
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), *argv, "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {k: v for k, v in reply.items() if k != "ok"}


def test_a_refused_op_with_json_prints_the_refusal_as_json_too(tmp_path, monkeypatch, capsys):
    """A script that parses standard output got nothing when the daemon refused: it gets the refusal as JSON, and
    the error line and exit status 1 as before."""
    import spadscan.daemon.client as client

    def refuse(path, op, timeout, **request):
        raise client.ControlError("nothing to pause (daemon is idle)")

    monkeypatch.setattr(client, "call", refuse)
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), "pause", "--json"]) == 1
    captured = capsys.readouterr()
    assert json.loads(captured.out) == {"ok": False, "error": "nothing to pause (daemon is idle)"}
    assert captured.err == "spadscan: error: nothing to pause (daemon is idle)\n"
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), "pause"]) == 1
    assert capsys.readouterr().out == "", "without --json: the error line alone"
