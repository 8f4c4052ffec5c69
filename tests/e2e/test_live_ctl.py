"""`spadscan ctl` shows a scan's live reconstruction: `status` adds it (read from the scan's recon/live/status.json,
beside the daemon's own reply), `wait` names it on its progress bar and, without a terminal, says in one line each
time it changes state. A daemon stand-in answers on a real Unix socket."""

from __future__ import annotations

import io
import json
import threading

import pytest

from spadscan.cli import main
from spadscan.commands.ctl import PauseNotes, live_status
from spadscan.protocol.live_status import LiveStatus, write_status

from status_daemon import StatusDaemon


@pytest.fixture
def daemon(sock_dir):
    """The stand-in, listening on a socket in the short sock_dir (one under a long TMPDIR's tmp_path cannot be
    bound); its path is the server's server_address."""
    server = StatusDaemon(str(sock_dir / "ctl.sock"), {})
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.01})
    thread.start()
    yield server
    server.shutdown()
    thread.join()
    server.server_close()


def live_folder(capture):
    folder = capture / "recon" / "live"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def test_status_shows_the_live_reconstruction_of_the_scan_in_flight(daemon, tmp_path, capsys):
    capture = tmp_path / "caps" / "mug"
    write_status(live_folder(capture), LiveStatus(views_used=24, views_published=30, steps=900, chamfer_mm=1.5,
                                                  views_planned=64, job="mug-fast"))
    daemon.reply = {"state": "scanning", "scan": "mug", "path": str(capture), "pose": 30, "poses": 64}
    assert main(["ctl", "--socket", daemon.server_address, "status"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["scan"] == "mug" and shown["live"]["views_used"] == 24 and shown["live"]["steps"] == 900
    assert shown["live"]["chamfer_mm"] == 1.5 and shown["live"]["state"] == "live" and shown["live"]["age_s"] >= 0


def test_status_after_the_scan_reads_the_last_scans_live_state(tmp_path):
    capture = tmp_path / "caps" / "cup"
    write_status(live_folder(capture), LiveStatus(views_used=64, views_published=64, steps=3000, state="done",
                                                  result=str(capture / "recon" / "cup-fast")))
    status = {"state": "idle", "scan": None, "last_scan": {"name": "cup", "state": "complete"},
              "daemon": {"captures": str(tmp_path / "caps")}}
    assert live_status(status)["state"] == "done"
    assert live_status({"state": "idle", "scan": None}) is None  # no scan yet: nothing to show


def test_status_without_a_live_job_is_as_before(daemon, tmp_path, capsys):
    daemon.reply = {"state": "scanning", "scan": "mug", "path": str(tmp_path / "mug")}
    assert main(["ctl", "--socket", daemon.server_address, "status"]) == 0
    assert "live" not in json.loads(capsys.readouterr().out)


def test_a_damaged_live_status_is_named_not_fatal(daemon, tmp_path, capsys):
    capture = tmp_path / "mug"
    (live_folder(capture) / "status.json").write_text("{torn")
    daemon.reply = {"state": "scanning", "scan": "mug", "path": str(capture)}
    assert main(["ctl", "--socket", daemon.server_address, "status"]) == 0
    assert "unreadable live status" in json.loads(capsys.readouterr().out)["live"]["error"]


def test_wait_without_a_terminal_says_when_the_live_state_changes(tmp_path):
    capture = tmp_path / "mug"
    folder = live_folder(capture)
    stream = io.StringIO()
    notes = PauseNotes("mug", stream)
    status = {"state": "scanning", "scan": "mug", "path": str(capture)}
    notes.update(status)  # no live job yet: nothing
    write_status(folder, LiveStatus(views_used=0, views_published=3, steps=0, state="waiting"))
    notes.update(status)
    write_status(folder, LiveStatus(views_used=8, views_published=9, steps=40, state="live"))
    notes.update(status)
    write_status(folder, LiveStatus(views_used=12, views_published=12, steps=300, state="live"))
    notes.update(status)  # the same state: no new line
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2
    assert "waiting for views" in lines[0] and "following the scan: 8/9 views, 40 steps" in lines[1]
