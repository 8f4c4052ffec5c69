"""The daemon's device lifecycle and request dispatch (in-process; the subprocess tests are test_daemon_process)."""

from __future__ import annotations

import asyncio
import os
import signal
import time
from pathlib import Path

import pytest

from spadscan.daemon.app import DeviceSession, Dispatcher
from spadscan.daemon.devices import Device
from spadscan.daemon.scan_end import ScanEnd
from spadscan.protocol.errors import ConfigError, DeviceError


class Recorder(Device):
    """A device that logs its lifecycle and can fail or hang in one step."""

    def __init__(self, name: str, log: list, fail: str | None = None, hang: str | None = None, delay: float = 0.0):
        self.name, self.log, self.fail, self.hang, self.delay = name, log, fail, hang, delay

    async def _step(self, step: str) -> None:
        self.log.append((self.name, step, "begin"))
        await asyncio.sleep(self.delay)
        if step == self.hang:
            await asyncio.sleep(3600)
        if step == self.fail:
            raise DeviceError(f"{self.name}: {step} refused")
        self.log.append((self.name, step, "end"))

    async def connect(self):
        await self._step("connect")

    async def prepare(self):
        await self._step("prepare")

    async def release(self):
        await self._step("release")

    async def close(self):
        await self._step("close")


def test_devices_connect_in_parallel_and_always_release(arun):
    log = []

    async def scenario():
        a, b = Recorder("arm", log, delay=0.05), Recorder("sensor", log, delay=0.05)
        with pytest.raises(RuntimeError, match="body failed"):
            async with DeviceSession([a, b]):
                log.append(("body",))
                raise RuntimeError("body failed")

    arun(scenario())
    # Both connects begin before either ends: parallel.
    assert log[:2] == [("arm", "connect", "begin"), ("sensor", "connect", "begin")]
    assert ("body",) in log
    for dev in ("arm", "sensor"):
        for step in ("release", "close"):
            assert (dev, step, "end") in log
    assert log.index(("arm", "release", "end")) < log.index(("arm", "close", "begin"))


def test_every_failed_device_is_reported_in_one_error(arun):
    log = []

    async def scenario():
        devices = [Recorder("arm", log, fail="connect"), Recorder("sensor", log, hang="connect"),
                   Recorder("light", log)]
        session = DeviceSession(devices, timeouts={"connect": 0.2})
        with pytest.raises(DeviceError) as info:
            async with session:
                log.append(("body",))
        return str(info.value)

    msg = arun(scenario())
    assert msg.startswith("rig did not start: ")
    assert "arm: connect refused" in msg and "sensor: connect did not finish within 0.2 s" in msg
    assert "light" not in msg and "\n" not in msg
    assert ("body",) not in log
    assert ("light", "release", "end") in log and ("light", "close", "end") in log  # the good one is let go too
    assert not any(step == "prepare" for _, step, *_ in log)


def test_release_failure_is_reported(arun):
    log = []

    async def scenario():
        async with DeviceSession([Recorder("arm", log, fail="release"), Recorder("sensor", log)]):
            pass

    with pytest.raises(DeviceError, match="rig did not shut down cleanly: arm: release refused"):
        arun(scenario())
    assert ("arm", "close", "end") in log and ("sensor", "release", "end") in log


class FakeRunner:
    def __init__(self):
        self.calls = []

    def status(self):
        return {"state": "idle"}

    async def status_now(self):
        return self.status()

    async def start(self, name, options):
        self.calls.append(("start", name, options))
        return {"state": "scanning", "scan": name}

    class aborts:  # noqa: N801  (the runner's AbortBook: nothing to write again)
        @staticmethod
        async def retry():
            pass

    async def abort(self, reason):
        self.calls.append(("abort", reason))
        return {"state": "idle"}

    async def wait_end(self, name):
        return ScanEnd("complete", None, {"state": "idle"}, time.monotonic())


def test_dispatcher(arun, tmp_path, sock_dir):
    from spadscan.daemon.config import config_from_dict

    cfg = config_from_dict({"captures": str(tmp_path), "socket": str(sock_dir / "s.sock"),
                            "sensor": {"backend": "sim", "mesh": "builtin:sphere"}}, tmp_path / "rig.toml")

    async def scenario():
        runner, stop = FakeRunner(), asyncio.Event()
        d = Dispatcher(runner, stop, cfg)
        out = [await d({"op": "status"}), await d({"op": "scan", "name": "n", "options": {"views": 3}}),
               await d({"op": "abort"}), await d({"op": "wait", "name": "n"})]
        for bad, word in (({"op": "dance"}, "unknown op 'dance'"), ({"op": "status", "x": 1}, "takes no x"),
                          ({"op": "scan", "options": [1]}, "JSON object"), ({"op": "wait"}, "needs a scan")):
            with pytest.raises(ConfigError, match=word):
                await d(bad)
        assert not stop.is_set()
        out.append(await d({"op": "shutdown"}))
        await asyncio.sleep(0)
        return out, runner.calls, stop.is_set()

    out, calls, stopped = arun(scenario())
    assert out[0]["state"] == "idle" and out[0]["daemon"]["socket"] == str(sock_dir / "s.sock")
    assert calls == [("start", "n", {"views": 3}), ("abort", "aborted by user")]
    ended = out[3]["status"]  # the status as the scan ended, with the daemon's block (as `status` has it)
    assert out[3] == {"name": "n", "state": "complete", "status": ended}
    assert ended["state"] == "idle" and ended["daemon"]["socket"] == str(sock_dir / "s.sock")
    assert out[4] == {"stopping": True} and stopped


def test_an_abort_reason_is_one_line_before_it_is_cut(arun, tmp_path, sock_dir):
    """`ctl abort --reason` may carry line breaks; the capture, the status and the log take one line, and the
    200-character cut counts what is shown, not runs of whitespace."""
    from spadscan.daemon.config import config_from_dict

    cfg = config_from_dict({"captures": str(tmp_path), "socket": str(sock_dir / "s.sock"),
                            "sensor": {"backend": "sim", "mesh": "builtin:sphere"}}, tmp_path / "rig.toml")

    async def scenario():
        runner = FakeRunner()
        d = Dispatcher(runner, asyncio.Event(), cfg)
        for reason in ("sensor cable\n  unplugged\tby Bob\n", " " * 300 + "x" * 300, " \n "):
            await d({"op": "abort", "reason": reason})
        return runner.calls

    assert arun(scenario()) == [("abort", "sensor cable unplugged by Bob"), ("abort", "x" * 200),
                                ("abort", "aborted by user")]


# ---- spadscan daemon --check -----------------------------------------------------------------------------------------
def write_check_rig(tmp_path, sock_dir, sensor: str) -> Path:
    rig = tmp_path / "rig.toml"
    rig.write_text(f'captures = "caps"\nsocket = "{sock_dir / "d.sock"}"\n[arm]\nbackend = "sim"\n'
                   f'[sensor]\n{sensor}\n[scan]\nviews = 8\nradius_m = 0.3\ntarget = [0, 0, 0.1]\n')
    return rig


def check(rig, capsys) -> tuple[int, str, str]:
    from spadscan.cli import main

    code = main(["daemon", "--config", str(rig), "--check"])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("what", ["builtin", "mesh-file", "firmware", "socket"])
def test_check_refuses_what_start_up_refuses(tmp_path, sock_dir, capsys, what):
    """`--check` runs start-up's checks: an unknown built-in scene, a mesh file with no triangles, a firmware image
    that is not Intel HEX, a socket path taken by a regular file; one line, exit 1, nothing created."""
    (tmp_path / "garbage.stl").write_text("solid x\nthis is not a mesh\n")
    (tmp_path / "app.hex").write_text("this is not intel hex\n")
    sensor = {"builtin": 'backend = "sim"\nmesh = "builtin:nope"',
              "mesh-file": 'backend = "sim"\nmesh = "garbage.stl"',
              "firmware": 'backend = "i2c"\nbus = 1\nfirmware = "app.hex"',
              "socket": 'backend = "sim"\nmesh = "builtin:sphere"'}[what]
    if what == "socket":
        (sock_dir / "d.sock").write_text("a regular file")
    code, out, err = check(write_check_rig(tmp_path, sock_dir, sensor), capsys)
    assert code == 1 and out == "" and err.count("\n") == 1 and err.startswith("spadscan: error:"), err
    assert {"builtin": "nope", "mesh-file": "garbage.stl", "firmware": "firmware", "socket": "not a socket"}[what] \
        in err
    where = {"builtin": "[sensor] mesh: ", "mesh-file": "[sensor] mesh: ", "firmware": "[sensor] firmware: ",
             "socket": "socket path "}[what]
    assert err.startswith(f"spadscan: error: {tmp_path / 'rig.toml'}: {where}"), err  # FILE: [section] key
    assert not (tmp_path / "caps").exists()


def test_check_passes_a_good_config_and_touches_nothing(tmp_path, sock_dir, capsys):
    code, out, err = check(write_check_rig(tmp_path, sock_dir, 'backend = "sim"\nmesh = "builtin:sphere"'), capsys)
    assert code == 0 and "ok (sim arm, sim sensor, default scan of 8 poses" in out, err
    assert not (tmp_path / "caps").exists() and not (sock_dir / "d.sock").exists()



@pytest.mark.parametrize("sensor, word", [
    ('backend = "serial"\nport = "{tmp}/ttyACM9"', "port {tmp}/ttyACM9: no such device"),
    ('backend = "i2c"\nbus = 250\nfirmware = "app.hex"', "bus 250: /dev/i2c-250: no such device")])
def test_check_refuses_a_sensor_device_that_is_not_there(tmp_path, sock_dir, capsys, sensor, word):
    """A serial port or I2C bus that does not exist is refused by `--check` (looking at the path opens nothing), as
    by start-up, in one line naming the file and the key."""
    (tmp_path / "app.hex").write_text(":0400000001020304F2\n:00000001FF\n")  # a valid image: one record, then EOF
    rig = write_check_rig(tmp_path, sock_dir, sensor.format(tmp=tmp_path))
    code, out, err = check(rig, capsys)
    assert code == 1 and out == "" and err.count("\n") == 1, err
    assert f"{rig}: [sensor] " + word.format(tmp=tmp_path) in err
    assert not (tmp_path / "caps").exists()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_while_the_devices_connect_ends_the_start_up(tmp_path, sock_dir, arun, sig):
    """An arm that never answers its connect (a wrong address, a controller that accepts and stays silent): a stop
    signal ends the start-up at once, releases and closes what connected, and no socket is ever opened."""
    from spadscan.daemon.app import serve
    from spadscan.daemon.config import config_from_dict

    cfg = config_from_dict({"captures": str(tmp_path), "socket": str(sock_dir / "s.sock"),
                            "sensor": {"mesh": "builtin:sphere"}}, tmp_path / "rig.toml")
    log = []
    arm, sensor = Recorder("arm", log, hang="connect"), Recorder("sensor", log)

    async def scenario():
        serving = asyncio.ensure_future(serve(cfg, arm, sensor))
        while ("arm", "connect", "begin") not in log:
            await asyncio.sleep(0.01)
        os.kill(os.getpid(), sig)
        await serving

    arun(scenario(), timeout_s=60)  # the arm's connect alone would hang an hour
    assert ("arm", "connect", "end") not in log
    for dev in ("arm", "sensor"):
        assert (dev, "release", "end") in log and (dev, "close", "end") in log
    assert not (sock_dir / "s.sock").exists()
