"""One writer per capture, across processes: a capture whose writer is open in another process (a second daemon
started on the same captures root after its lock file was deleted) is neither reopened, nor taken over, nor aborted,
nor cleaned of its half-written chunks here. Also: a restarted daemon leaves ended captures alone, and a scan whose
pause was withdrawn one pose before its end is not marked complete short of that pose."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import threading

import pytest

from spadscan.daemon.runner import ScanRunner
from spadscan.daemon.scan_job import find_interrupted
from spadscan.protocol.capture_format import MANIFEST, read_json, write_json_atomic
from spadscan.protocol.capture_reader import CaptureReader
from spadscan.protocol.capture_writer import CaptureWriter, writer_lock_held
from spadscan.protocol.errors import CaptureError, ConfigError

from test_runner import until
from test_runner_resume import a_daemon, interrupt, make_cfg

ELSEWHERE = "another process is writing this capture"

HOLDER = """
import sys
from spadscan.protocol.capture_writer import CaptureWriter
w = CaptureWriter.resume(sys.argv[1])
print("open", flush=True)
sys.stdin.read()  # held until the test closes our stdin
"""


class Holder:
    """A writer of the capture at `path` open in another process, until `close`."""

    def __init__(self, path):
        self.proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(path)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()  # waits for the writer to be open (or the process to end)
        if line.strip() != "open":
            said = self.proc.stderr.read()
            self.close()
            raise AssertionError(f"the holder did not open the capture: {said}")

    def close(self):
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            self.proc.stdin.close()
        self.proc.wait(timeout=30)
        for f in (self.proc.stdout, self.proc.stderr):
            f.close()


@pytest.fixture
def interrupted(arun, tmp_path):
    """(cfg, capture path) of scan 'mix', interrupted by a daemon that stopped with a few poses published."""
    cfg = make_cfg(tmp_path)
    arun(interrupt(cfg))
    return cfg, tmp_path / "caps" / "mix"


def test_a_capture_open_in_another_process_is_not_reopened_and_keeps_its_temporary_chunk(interrupted):
    _, path = interrupted
    holder = Holder(path)
    try:
        half = path / ".tmp-chunk-000999"
        half.mkdir()  # the other writer's chunk being written
        with pytest.raises(CaptureError, match=ELSEWHERE) as refused:
            CaptureWriter.resume(path)
        assert "\n" not in str(refused.value)
        assert half.is_dir() and writer_lock_held(path)
    finally:
        holder.close()
    assert not writer_lock_held(path)  # the kernel drops it with its holder
    w = CaptureWriter.resume(path)
    try:
        assert not half.exists()  # no writer is left to finish it: dropped, as ever
    finally:
        w.close()


def test_a_writer_closed_lets_another_process_open_the_capture(interrupted):
    _, path = interrupted
    first = CaptureWriter.resume(path)
    second = CaptureWriter.resume(path)  # one process: its writers share the lock (the daemon reopens its scans)
    first.close()
    first.close()  # (closing twice releases once)
    with pytest.raises(AssertionError, match=ELSEWHERE):
        Holder(path)  # the second one still holds it
    second.close()
    Holder(path).close()


def test_a_restarted_daemon_does_not_take_over_a_scan_another_process_writes(arun, interrupted):
    cfg, path = interrupted
    holder = Holder(path)
    half = path / ".tmp-chunk-000999"
    half.mkdir()

    async def restart():
        async with a_daemon(cfg) as (runner, _):
            await runner.recover()
            status = runner.status()
            with pytest.raises(ConfigError, match="not aborted: another process is writing it"):
                await runner.abort(name="mix")
            return runner.job, runner.stuck, status

    try:
        job, stuck, status = arun(restart())
        assert job is None and status["state"] == "idle", status
        assert stuck is not None and stuck["scan"] == "mix" and ELSEWHERE in stuck["cause"], stuck
        assert "cannot take over interrupted scan 'mix'" in status["last_error"], status
        assert "ctl abort" not in status["last_error"]  # no advice to end a scan someone else is writing
        assert half.is_dir()
        assert read_json(path / MANIFEST)["state"] == "running"
    finally:
        holder.close()


@pytest.mark.parametrize("state", ["complete", "aborted"])
def test_a_restarted_daemon_leaves_an_ended_capture_alone(arun, interrupted, state):
    cfg, path = interrupted
    manifest = read_json(path / MANIFEST)
    manifest.pop("paused", None)
    manifest.update(state=state, reason=None if state == "complete" else "stopped by hand")
    write_json_atomic(path / MANIFEST, manifest)
    assert find_interrupted(path.parent) == []

    async def restart():
        async with a_daemon(cfg) as (runner, _):
            await runner.recover()
            return runner.job, runner.stuck, runner.status()

    job, stuck, status = arun(restart())
    assert job is None and stuck is None and status["state"] == "idle", status
    assert read_json(path / MANIFEST)["state"] == state
    assert read_json(path / MANIFEST)["reason"] == manifest["reason"]


def test_a_pause_withdrawn_one_pose_before_the_end_takes_the_last_pose(arun, tmp_path, monkeypatch):
    """The pause stops the pose loop with the last pose not taken; withdrawn before the loop looks again, the scan
    goes on and takes that pose: it is not marked complete one pose short."""
    cfg = make_cfg(tmp_path)
    n = cfg.scan.views
    entered = {n - 3: threading.Event(), n - 2: threading.Event()}
    gate = {n - 3: threading.Event(), n - 2: threading.Event()}
    publish = ScanRunner._publish

    def held_publish(writer, measurements):
        pose = measurements[0].pose_index
        if pose in entered:
            entered[pose].set()
            assert gate[pose].wait(30), f"pose {pose}'s publish was never let through"
        publish(writer, measurements)

    monkeypatch.setattr(ScanRunner, "_publish", staticmethod(held_publish))

    async def scan():
        async with a_daemon(cfg) as (runner, _):
            try:
                await runner.start("mix")
                # Pose n - 3's publish holds pose n - 2's iteration: the pause is asked before the loop looks at
                # pose n - 1, so it stops there with pose n - 1 not taken.
                assert await asyncio.to_thread(entered[n - 3].wait, 30)
                await runner.pause()
                assert runner.state == "pausing"
                gate[n - 3].set()
                # Pose n - 2's publish is the one the stopped loop waits for: the pause is withdrawn meanwhile.
                assert await asyncio.to_thread(entered[n - 2].wait, 30)
                await runner.resume()
                gate[n - 2].set()
                await until(lambda: runner.job is None or runner.state == "idle", "the scan's end", 60)
                return runner.status()
            finally:
                for g in gate.values():
                    g.set()

    status = arun(scan())
    reader = CaptureReader(tmp_path / "caps" / "mix")
    assert reader.state == "complete", status
    assert sorted(set(reader.load().pose_indices.tolist())) == list(range(n))
