"""An interrupted `spadscan simulate` says what it left behind and how to go on: it printed only "spadscan:
interrupted", and the partial capture it left, marked aborted, then refused the same command run again."""

from __future__ import annotations

import json
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from process_helpers import reaped
from spadscan.cli import main

VIEWS = 4000
"""Enough views, four to a chunk, that the simulation still runs when the test stops it."""


def views_held(cap: Path) -> int:
    """The views (pose indices) the published chunks of `cap` hold."""
    return len({m["pose_index"] for meta in cap.glob("chunk-*/meta.json")
                for m in json.loads(meta.read_text())["measurements"]})


@pytest.mark.parametrize("how", [pytest.param(signal.SIGINT, id="ctrl-c"), pytest.param(signal.SIGTERM, id="SIGTERM")])
def test_an_interrupted_simulation_says_what_it_left_and_how_to_go_on(tmp_path, how):
    out = tmp_path / "caps" / "simint"
    argv = [sys.executable, "-m", "spadscan.cli", "simulate", "builtin:sphere", "--sensor", "tmf8820", "--out",
            str(out), "--views", str(VIEWS), "--chunk-size", "4", "--no-progress"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with reaped(proc):
        deadline = time.monotonic() + 120
        while not (out / "chunk-000001").is_dir() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, "the simulation ended before it could be stopped"
        proc.send_signal(how)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    held = views_held(out)
    assert 8 <= held < VIEWS
    assert err.splitlines()[-2:] == [
        f"spadscan simulate: interrupted after {held} of {VIEWS} views; the partial capture {out} is marked aborted: "
        f"remove it (rm -r {shlex.quote(str(out))}) and run again, or give --out a new folder",
        "spadscan: interrupted"], err
    assert json.loads((out / "scan.json").read_text())["state"] == "aborted"


def test_an_interruption_before_anything_was_written_says_nothing_more(tmp_path, capsys, monkeypatch):
    from spadscan.protocol import simulator

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(simulator, "simulate_capture", stopped)
    assert main(["simulate", "builtin:sphere", "--out", str(tmp_path / "cap"), "--views", "8", "--no-progress"]) == 130
    assert capsys.readouterr().err == "spadscan: interrupted\n"
    assert not (tmp_path / "cap").exists()


def test_a_capture_that_was_there_before_is_not_said_to_be_left_by_the_run(tmp_path, capsys, monkeypatch):
    """A folder that held an aborted capture (refused by the writer) is none of an interrupted run's doing."""
    from spadscan.protocol import simulator

    cap = tmp_path / "cap"
    assert main(["simulate", "builtin:sphere", "--out", str(cap), "--views", "8", "--no-progress"]) == 0
    manifest = json.loads((cap / "scan.json").read_text())
    (cap / "scan.json").write_text(json.dumps({**manifest, "state": "aborted"}))
    capsys.readouterr()

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(simulator, "simulate_capture", stopped)
    assert main(["simulate", "builtin:sphere", "--out", str(cap), "--views", "8", "--no-progress"]) == 130
    assert capsys.readouterr().err == "spadscan: interrupted\n"
