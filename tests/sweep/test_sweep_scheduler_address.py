"""--scheduler pointed at something that is not a Dask scheduler: an HTTP server (the dashboard's port, 8787, is the
usual mix-up with 8786), a server that talks first in another protocol (sshd), a Dask worker, a closed port, and
tls://. Each ends in one line naming the address, within the connect timeout (short here, a parameter)."""

from __future__ import annotations

import socket
import socketserver
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from spadscan.cli import main
from spadscan.protocol.errors import ConfigError
from spadscan.sweep import runner
from spadscan.sweep.checks import check_scheduler_address
from spadscan.sweep.plan import make_plan
from spadscan.sweep.spec import load_spec

from sweep_helpers import write_tiny

TIMEOUT_S = 2.0
SLACK_S = 10.0
"""Beyond the timeout, for a busy machine: the refusal comes at the deadline, not minutes later."""
SSH_BANNER = b"SSH-2.0-OpenSSH_8.9p1 Ubuntu-3ubuntu0.10\r\n"


class _Quiet(BaseHTTPRequestHandler):
    def do_GET(self):  # noqa: N802 - http.server's name
        self.send_response(200)
        self.end_headers()

    def log_message(self, *args):  # the test's output stays clean
        pass


class _Banner(socketserver.BaseRequestHandler):
    """Says its banner, then waits for the client, as sshd does (until the client or the test ends it)."""

    def handle(self):
        self.request.sendall(SSH_BANNER)
        self.server.stopping.wait()  # type: ignore[attr-defined]


class _BannerServer(socketserver.ThreadingTCPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self):
        super().__init__(("127.0.0.1", 0), _Banner)
        self.stopping = threading.Event()


def _serve(server):
    """Serve `server` in a thread; yields its tcp:// address; the server is stopped when the test ends."""
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"tcp://127.0.0.1:{server.server_address[1]}"
    finally:
        getattr(server, "stopping", threading.Event()).set()
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)


@pytest.fixture
def http_server():
    yield from _serve(ThreadingHTTPServer(("127.0.0.1", 0), _Quiet))


@pytest.fixture
def ssh_like_server():
    yield from _serve(_BannerServer())


@pytest.fixture
def closed_port():
    with socket.socket() as s:  # a port just free: nothing listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"tcp://127.0.0.1:{port}"


def refused_in_time(address: str) -> str:
    start = time.monotonic()
    with pytest.raises(ConfigError) as err:
        runner.probe_scheduler(address, TIMEOUT_S)
    assert time.monotonic() - start < TIMEOUT_S + SLACK_S
    message = str(err.value)
    assert message.startswith(f"{address} is not a reachable Dask scheduler") and "\n" not in message, message
    return message


def test_an_http_server_such_as_the_dashboard_is_refused_at_the_deadline(http_server):
    message = refused_in_time(http_server)
    assert "8786" in message or "protocol" in message, message


def test_a_server_that_talks_another_protocol_first_is_refused(ssh_like_server):
    message = refused_in_time(ssh_like_server)
    assert "Traceback" not in message and "EiB" not in message, message


def test_a_closed_port_is_refused_at_the_deadline(closed_port):
    refused_in_time(closed_port)


def test_a_dask_worker_is_not_taken_for_its_scheduler():
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        worker = next(iter(cluster.scheduler.workers))
        assert "answers as a Dask Worker" in refused_in_time(worker)
        runner.probe_scheduler(cluster.scheduler_address, TIMEOUT_S)  # the scheduler itself passes


def test_run_sweep_refuses_an_http_server_in_one_line_within_its_timeout(http_server, tmp_path):
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    start = time.monotonic()
    with pytest.raises(ConfigError, match="is not a reachable Dask scheduler"):
        runner.run_sweep(plan, tmp_path / "out", scheduler=http_server, progress=False, connect_timeout_s=TIMEOUT_S)
    assert time.monotonic() - start < TIMEOUT_S + SLACK_S


@pytest.mark.parametrize("server", ["http_server", "ssh_like_server"])
def test_the_command_says_one_line_within_its_timeout(server, request, tmp_path, monkeypatch, capsys):
    address = request.getfixturevalue(server)
    monkeypatch.setattr(runner, "CONNECT_TIMEOUT_S", TIMEOUT_S)
    tiny = str(write_tiny(tmp_path))
    start = time.monotonic()
    assert main(["sweep", tiny, "--out", str(tmp_path / "out"), "--scheduler", address, "--no-progress"]) == 1
    assert time.monotonic() - start < TIMEOUT_S + SLACK_S
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("spadscan: error: ")]
    assert len(errors) == 1 and f"{address} is not a reachable Dask scheduler" in errors[0], err


def test_tls_is_refused_in_one_line_before_anything_runs(tmp_path, capsys):
    with pytest.raises(ConfigError, match="needs a Dask security configuration") as err:
        check_scheduler_address("tls://127.0.0.1:8786")
    assert "\n" not in str(err.value) and "tcp://" in str(err.value)
    tiny = str(write_tiny(tmp_path))
    for extra in (["--dry-run"], ["--no-progress"]):
        assert main(["sweep", tiny, "--out", str(tmp_path / "out"), "--scheduler", "tls://127.0.0.1:8786",
                     *extra]) == 1
        err = capsys.readouterr().err
        assert "Traceback" not in err and "security configuration" in err, err
    assert not (tmp_path / "out").exists()


def _tree(folder) -> dict:
    """Every path under `folder` with its size and modification time."""
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*"))}


def test_a_refused_scheduler_leaves_no_folder_and_an_existing_one_as_it_was(closed_port, tmp_path):
    """The scheduler is asked before the results folder is made or opened: a run it refuses writes nothing."""
    plan = make_plan(load_spec(write_tiny(tmp_path)))
    with pytest.raises(ConfigError, match="is not a reachable Dask scheduler"):
        runner.run_sweep(plan, tmp_path / "out", scheduler=closed_port, progress=False, connect_timeout_s=TIMEOUT_S)
    assert not (tmp_path / "out").exists()
    from spadscan.sweep.store import SweepDir

    out = SweepDir(tmp_path / "earlier")
    out.open(plan)
    out.close()
    before = _tree(out.path)
    with pytest.raises(ConfigError, match="is not a reachable Dask scheduler"):
        runner.run_sweep(plan, out.path, scheduler=closed_port, progress=False, connect_timeout_s=TIMEOUT_S)
    assert _tree(out.path) == before
