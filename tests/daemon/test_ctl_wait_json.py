"""`spadscan ctl wait --json`: like every other operation, `wait` takes --json. Its standard output is then one line
of JSON once the wait ends: what `status --json` prints at that moment plus `wait` (the scan, how the wait ended,
how long it took); an error or Ctrl-C is {"ok": false, "error": ..., "wait": ...} there, beside its one line on
stderr. The progress bar and the pause notes stay on stderr."""

from __future__ import annotations

import json
import sys

import pytest

from spadscan.cli import main
from spadscan.protocol.live_status import LiveStatus, write_status

from test_ctl import POSES, Terminal, fake_daemon, interrupted_wait  # noqa: F401  (fake_daemon: the fixture)


def one_json_line(out: str) -> dict:
    assert out.endswith("\n") and out.count("\n") == 1, out
    return json.loads(out)


def test_wait_with_json_prints_the_status_at_the_end_and_how_the_wait_ended(fake_daemon, capsys):
    """Before: argparse refused --json (exit 2)."""
    server, path = fake_daemon
    server.pose = POSES
    assert main(["ctl", "--socket", path, "wait", "mug", "--json"]) == 0
    out, err = capsys.readouterr()
    shown = one_json_line(out)
    assert err == ""
    waited = shown.pop("wait")
    assert waited["name"] == "mug" and waited["ended"] == "complete" and waited["waited_s"] >= 0
    assert set(waited) == {"name", "ended", "waited_s"}
    assert main(["ctl", "--socket", path, "status", "--json"]) == 0
    assert shown == one_json_line(capsys.readouterr().out), "the rest is what `status --json` prints then"


def test_wait_with_json_gives_the_scans_live_reconstruction_as_status_does(tmp_path, monkeypatch, capsys):
    import spadscan.daemon.client as client

    capture = tmp_path / "caps" / "mug"
    (capture / "recon" / "live").mkdir(parents=True)
    write_status(capture / "recon" / "live", LiveStatus(views_used=6, views_published=6, steps=90, state="final",
                                                        job="mug-fast"))
    status = {"state": "idle", "scan": None, "last_scan": {"name": "mug", "state": "aborted"},
              "daemon": {"captures": str(tmp_path / "caps")}}
    replies = {"wait": {"ok": True, "name": "mug", "state": "aborted", "status": status},
               "status": {"ok": True, **status}}
    monkeypatch.setattr(client, "call", lambda path, op, timeout, **request: dict(replies[op]))
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), "wait", "mug", "--json"]) == 1
    out, err = capsys.readouterr()
    shown = one_json_line(out)
    assert err == "spadscan: scan 'mug' ended aborted\n", err
    assert shown["wait"]["ended"] == "aborted" and shown["last_scan"] == {"name": "mug", "state": "aborted"}
    assert shown["live"]["state"] == "final" and shown["live"]["steps"] == 90


@pytest.mark.parametrize("case", ["timeout", "no daemon", "refused"])
def test_a_wait_that_fails_with_json_is_json_on_stdout_beside_one_error_line(case, fake_daemon, tmp_path, monkeypatch,
                                                                              capsys):
    server, path = fake_daemon
    server.pose, server.step = 3, 0  # a healthy scan that is not done in time
    monkeypatch.setattr("spadscan.commands.ctl.PROGRESS_POLL_S", 0.01)
    argv = {"timeout": ["--socket", path, "--timeout", "0.2", "wait", "mug"],
            "no daemon": ["--socket", str(tmp_path / "none.sock"), "wait", "mug"],
            "refused": ["--socket", path, "wait", "mug"]}[case]
    if case == "refused":
        from spadscan.daemon.client import ControlError
        import spadscan.daemon.client as client

        def refuse(path, op, timeout, **request):
            raise ControlError("no scan named 'mug' is running or finished in /caps")

        monkeypatch.setattr(client, "call", refuse)
    assert main(["ctl", *argv, "--json"]) == 1
    out, err = capsys.readouterr()
    shown = one_json_line(out)
    assert err.startswith("spadscan: error: ") and err.count("\n") == 1, err
    assert shown["ok"] is False and shown["error"] == err[len("spadscan: error: "):-1]
    assert shown["wait"]["name"] == "mug" and shown["wait"]["ended"] == ("timeout" if case == "timeout" else "error")
    if case == "timeout":
        assert shown["error"] == "scan 'mug' still scanning at pose 3/6 after 0.2 s"
    assert main(["ctl", *argv]) == 1
    assert capsys.readouterr() == ("", err), "without --json: the error line alone, as before"


def test_the_progress_bar_stays_off_standard_output_with_json(fake_daemon, monkeypatch, capsys):
    """Both outputs terminals: the bar still goes to stderr only, and stdout holds the one JSON line."""
    server, path = fake_daemon
    stdout, stderr = Terminal(), Terminal()
    monkeypatch.setattr(sys, "stdout", stdout)
    monkeypatch.setattr(sys, "stderr", stderr)
    monkeypatch.setattr("spadscan.commands.ctl.PROGRESS_POLL_S", 0.01)
    assert main(["ctl", "--socket", path, "wait", "mug", "--json"]) == 0
    assert one_json_line(stdout.getvalue())["wait"]["ended"] == "complete"
    assert f"{POSES}/{POSES}" in stderr.getvalue() and "complete" in stderr.getvalue()
    assert "status" in server.requests  # the bar polled: it ran


def test_the_pause_notes_stay_on_stderr_with_json(fake_daemon, monkeypatch, capsys):
    server, path = fake_daemon
    server.pose, server.paused_polls = 2, 5
    monkeypatch.setattr("spadscan.commands.ctl.PROGRESS_POLL_S", 0.01)
    assert main(["ctl", "--socket", path, "wait", "mug", "--json"]) == 0
    out, err = capsys.readouterr()
    assert one_json_line(out)["wait"]["ended"] == "complete"
    assert err == "spadscan: scan 'mug' paused at pose 2/6: sensor silent: no frame (`spadscan ctl resume` " \
                  "continues it)\n", err


def test_ctrl_c_during_wait_with_json_says_so_on_stdout_too(fake_daemon):
    code, out, err = interrupted_wait(*fake_daemon, "--json")
    said = ("interrupted; scan 'mug' goes on in the daemon (`spadscan ctl wait mug` waits again, `spadscan ctl abort` "
            "stops it)")
    assert code == 130 and err == f"spadscan: {said}\n", err
    shown = one_json_line(out)
    assert shown["ok"] is False and shown["error"] == said and shown["wait"]["ended"] == "interrupted"


def test_the_help_says_wait_takes_json_and_where_the_progress_goes(capsys):
    with pytest.raises(SystemExit) as done:
        main(["ctl", "wait", "--help"])
    assert done.value.code == 0
    shown = " ".join(capsys.readouterr().out.split())
    assert "--json for scripts: standard output gets one line of JSON once the wait ends" in shown
    assert "The progress bar (on a terminal) or the pause and live notes stay on stderr" in shown
    with pytest.raises(SystemExit):
        main(["ctl", "--help"])
    assert "and so does `wait`" in " ".join(capsys.readouterr().out.split())


def test_wait_with_json_on_a_scan_that_ended_before_the_daemon_started_keeps_the_status_shape(tmp_path, monkeypatch,
                                                                                              capsys):
    """The daemon has no status of that scan's end (null): the line is still a status, the one the daemon answers
    now (here of another scan, being recorded), its `state` the daemon's as in every other case; the scan's end is
    `wait`'s (`ended`, and `reason`). Before: the line was the daemon's reply, {"name", "state": the scan's end,
    "reason"}, so that `state` meant one thing or the other."""
    import spadscan.daemon.client as client

    now = {"ok": True, "state": "scanning", "scan": "next", "daemon": {"captures": str(tmp_path / "caps")}}
    replies = {"wait": {"ok": True, "name": "mug", "state": "aborted", "reason": "lamp changed", "status": None},
               "status": now}
    monkeypatch.setattr(client, "call", lambda path, op, timeout, **request: dict(replies[op]))
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), "wait", "mug", "--json"]) == 1
    shown = one_json_line(capsys.readouterr().out)
    waited = shown.pop("wait")
    assert shown == {"state": "scanning", "scan": "next", "daemon": {"captures": str(tmp_path / "caps")}}, shown
    assert waited.pop("waited_s") >= 0
    assert waited == {"name": "mug", "ended": "aborted", "reason": "lamp changed"}


def test_wait_with_json_says_why_the_scan_ended_in_wait(tmp_path, monkeypatch, capsys):
    """The daemon's status as the scan ended: `wait` carries the reason too, where one was given."""
    import spadscan.daemon.client as client

    status = {"state": "idle", "scan": None, "last_scan": {"name": "mug", "state": "aborted"}}
    replies = {"wait": {"ok": True, "name": "mug", "state": "aborted", "reason": "lamp changed", "status": status}}
    monkeypatch.setattr(client, "call", lambda path, op, timeout, **request: dict(replies[op]))
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), "wait", "mug", "--json"]) == 1
    shown = one_json_line(capsys.readouterr().out)
    assert shown["state"] == "idle" and shown["wait"]["reason"] == "lamp changed", shown


def test_the_help_says_the_state_is_the_daemons_and_the_scans_end_is_waits(capsys):
    with pytest.raises(SystemExit):
        main(["ctl", "wait", "--help"])
    shown = " ".join(capsys.readouterr().out.split())
    assert "for a scan that ended before the daemon started, the daemon's status then" in shown, shown
    assert "`state` is always the daemon's" in shown and '"reason" where one was given for how it ended' in shown


def test_a_scan_whose_wait_fails_with_json_ends_with_the_error_on_stdout(tmp_path, monkeypatch, capsys):
    """`ctl scan --wait --json` whose wait runs out of time: standard output held the start's reply alone, so a
    script reading its last line read "scanning"; now the wait's {"ok": false, ...} line follows it."""
    from spadscan.daemon.client import ControlTimeout
    import spadscan.daemon.client as client

    def answer(path, op, timeout, **request):
        if op == "scan":
            return {"ok": True, "state": "scanning", "scan": "mug"}
        raise ControlTimeout("scan 'mug' still scanning at pose 3/6 after 0.2 s")

    monkeypatch.setattr(client, "call", answer)
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), "scan", "--wait", "--json", "--timeout", "0.2"]) == 1
    out, err = capsys.readouterr()
    started, failed = map(json.loads, out.splitlines())
    assert started == {"state": "scanning", "scan": "mug"}
    assert failed["ok"] is False and failed["wait"]["name"] == "mug" and failed["wait"]["ended"] == "timeout"
    assert err == f"spadscan: error: {failed['error']}\n", err
