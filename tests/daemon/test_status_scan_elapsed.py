"""`ctl status` says both how long the daemon has held the scan (`elapsed_s`: since this daemon started it or took it
over) and how long the scan has run (`scan_elapsed_s`: since its scan.json's created_utc, `started_utc`, across
takeovers): a daemon restarted mid-scan no longer reports the scan's time as its own few seconds."""

from __future__ import annotations

import datetime as dt
import json
import os
import signal
import time

import pytest

from spadscan.daemon.client import call
from spadscan.protocol.capture_reader import CaptureReader

from test_daemon_process import Daemons, daemons, spadscan, wait_for, write_rig  # noqa: F401  (daemons: the fixture)
from test_runner_resume import interrupt, make_cfg, restart

SLACK_S = 0.01
"""Rounding (status: 1 ms; created_utc: 1 ms) and the wall clock's slewing against the monotonic one."""


@pytest.mark.slow
def test_a_scan_taken_over_by_a_second_daemon_counts_its_time_from_its_start(tmp_path, sock_dir,
                                                                             daemons: Daemons):  # noqa: F811
    rig, sock = write_rig(tmp_path, auto=False, sock_dir=sock_dir)
    first = daemons.start(rig, sock)
    asked = time.time()
    r = spadscan("ctl", "--socket", sock, "scan", "--name", "long", "--views", "100", "--json")
    assert r.returncode == 0, r.stderr
    ran = wait_for(lambda: (s := call(sock, "status"))["pose"] >= 3 and s, "three poses")
    created = CaptureReader(tmp_path / "caps" / "long").manifest["created_utc"]
    assert ran["started_utc"] == created
    # The daemon that started the scan: both count from its start.
    assert ran["elapsed_s"] - SLACK_S <= ran["scan_elapsed_s"] <= time.time() - asked + SLACK_S, ran
    os.kill(first.pid, signal.SIGKILL)
    first.wait(timeout=30)

    second = daemons.start(rig, sock)
    r = spadscan("ctl", "--socket", sock, "status", "--json")
    now = time.time()
    assert r.returncode == 0, r.stderr
    status = json.loads(r.stdout)
    assert status["scan"] == "long" and status["state"] == "paused", (status, daemons.log(second))
    assert status["started_utc"] == created
    # The scan's time runs on from before the kill: at least what the first daemon said, plus this daemon's time.
    assert status["scan_elapsed_s"] >= ran["scan_elapsed_s"] + status["elapsed_s"] - SLACK_S, (ran, status)
    assert status["scan_elapsed_s"] <= now - asked + SLACK_S, status
    assert 0 <= status["elapsed_s"] <= now - asked - ran["scan_elapsed_s"] + SLACK_S, status


def dated(folder, created_utc) -> None:
    """Give the interrupted capture's scan.json another created_utc (None: none at all)."""
    path = folder / "scan.json"
    manifest = json.loads(path.read_text())
    if created_utc is None:
        del manifest["created_utc"]
    else:
        manifest["created_utc"] = created_utc
    path.write_text(json.dumps(manifest))


def test_the_time_a_scan_spent_before_its_takeover_counts_in_its_time_not_in_the_daemons(arun, tmp_path):
    """A scan begun two hours before its takeover (the earlier daemon's time and the time no daemon ran)."""
    cfg = make_cfg(tmp_path)
    arun(interrupt(cfg))
    dated_at = time.time()
    begun = dt.datetime.fromtimestamp(dated_at - 7200, dt.timezone.utc).isoformat(timespec="milliseconds")
    dated(tmp_path / "caps" / "mix", begun)
    status, refused = arun(restart(cfg))
    spent = time.time() - dated_at
    assert refused is None and status["started_utc"] == begun, status
    before = status["scan_elapsed_s"] - status["elapsed_s"]
    assert 7200 - SLACK_S <= before <= 7200 + spent + SLACK_S, status
    assert status["elapsed_s"] <= spent + SLACK_S, status


@pytest.mark.parametrize("created_utc", [None, "yesterday", 17])
def test_a_scan_json_that_does_not_say_when_the_scan_began_gives_no_scan_time(arun, tmp_path, created_utc):
    cfg = make_cfg(tmp_path)
    arun(interrupt(cfg))
    dated(tmp_path / "caps" / "mix", created_utc)
    status, refused = arun(restart(cfg))
    assert refused is None and status["state"] == "paused", status  # taken over all the same
    assert status["started_utc"] is None and status["scan_elapsed_s"] is None and status["elapsed_s"] >= 0, status


def test_a_start_in_the_future_counts_from_the_takeover(arun, tmp_path):
    """A wall clock set back since the scan began: the scan's time is never negative; it counts from now."""
    cfg = make_cfg(tmp_path)
    arun(interrupt(cfg))
    dated(tmp_path / "caps" / "mix", "2999-01-01T00:00:00.000+00:00")
    status, _ = arun(restart(cfg))
    assert abs(status["scan_elapsed_s"] - status["elapsed_s"]) <= 0.002, status
