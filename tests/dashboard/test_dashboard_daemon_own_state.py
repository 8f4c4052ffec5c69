"""The page says the daemon's state in the daemon's own words where the server can ask the daemon (`spadscan
dashboard` asks its control socket, as `spadscan ctl status` does): a scan the daemon could not take over reads "not
taken over", with the daemon's reason and way out, never "scanning" as its scan.json would have it; where the daemon
cannot be asked, the page tells the state from the files, saying why in the top line's tooltip."""

from __future__ import annotations

import pytest

from dashboard_helpers import serving, status
from page_helpers import add_pose, browser_page, start_scan
from spadscan.commands.dashboard import daemon_status
from spadscan.daemon.client import ControlError
from spadscan.dashboard.server import address

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine
ERROR = ("cannot take over interrupted scan 'vase': {root}/vase/chunk-000002/hists.npy: corrupt or truncated .npy "
         "(it ends inside its header); chunk-000002 cannot be read: move it out of {root}/vase (its poses are taken "
         "again), then `spadscan ctl resume vase`; or `spadscan ctl abort vase` ends the scan as aborted, keeping "
         "every chunk")


def stuck_reply(root) -> dict:
    """`spadscan ctl status`'s reply of a daemon on `root` that could not take scan vase over (daemon/runner.py)."""
    error = ERROR.format(root=root)
    return {"ok": True, "state": "idle", "scan": None, "last_error": error, "arm": "arm (sim)",
            "cannot_take_over": {"scan": "vase", "error": error},
            "daemon": {"pid": 1, "socket": "/tmp/x.sock", "captures": str(root), "uptime_s": 3.0}}


def scan_left_running(root) -> None:
    writer, poses = start_scan(root / "vase", 10)
    for i in range(4):
        add_pose(writer, poses, i)


def test_a_scan_the_daemon_could_not_take_over_reads_so_with_the_daemons_reason(tmp_path):
    scan_left_running(tmp_path)
    reply = stuck_reply(tmp_path)
    with serving(tmp_path, daemon_running=lambda r: True, daemon_status=lambda r: reply) as server, \
            browser_page() as (page, seen):
        page.goto(address(server))
        page.wait_for_function("() => document.querySelector('#daemon').textContent.includes('daemon:')",
                               timeout=WAIT_MS)
        top = page.locator("#daemon")
        assert top.text_content() == " \u00b7 daemon: idle \u00b7 " + reply["cannot_take_over"]["error"]
        assert top.get_attribute("class") == "down"
        cell = page.locator('#scans tr[data-scan="vase"] td.state-not_taken_over')
        assert cell.text_content() == "not taken over"
        assert cell.get_attribute("title") == reply["cannot_take_over"]["error"]
        assert page.locator("#current-state").text_content().startswith("not taken over (cannot take over ")
        assert "scanning" not in page.locator("header").inner_text()
        assert "scanning" not in page.locator("#scans").inner_text()
    assert not seen.errors, seen.errors


def test_where_the_daemon_cannot_be_asked_the_page_says_why_and_reads_the_files(tmp_path):
    scan_left_running(tmp_path)
    ask = daemon_status(str(tmp_path / "no.sock"))  # the CLI's own asking, on a socket nobody serves
    with pytest.raises(ControlError):
        ask(tmp_path)
    with serving(tmp_path, daemon_running=lambda r: True, daemon_status=ask) as server:
        answer = status(server)
        assert answer["daemon_status"] is None
        assert answer["daemon_status_note"].startswith("the daemon's own state cannot be asked (no daemon is "
                                                       "listening on "), answer["daemon_status_note"]
        assert answer["scans"][0]["state"] == "running"
        with browser_page() as (page, seen):
            page.goto(address(server))
            page.wait_for_function("() => document.querySelector('#daemon').textContent.includes('daemon:')",
                                   timeout=WAIT_MS)
            assert page.locator("#daemon").text_content() == " \u00b7 daemon: scanning vase"
            assert page.locator("#daemon").get_attribute("title") == answer["daemon_status_note"]
    assert not seen.errors, seen.errors
