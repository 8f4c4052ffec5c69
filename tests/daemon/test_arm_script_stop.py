"""The UR arm's control script ends with its session. An orderly close stops it (ur_rtde's stopScript: disconnect()
alone leaves it running on the controller), also after a failed pre-check; the controller's watchdog is armed as soon
as the client connects, kept kicked while the daemon waits, and is what stops the script when the client process dies.
The daemon and its ur_rtde process judge a held arm with one predicate (no stopScript where the daemon declined).
Real ur_rtde client, simulated controller in a child process on loopback (the predicate and the flags: in-process)."""

from __future__ import annotations

import asyncio
import itertools
import logging
import os
import re
import signal
import time

import numpy as np
import pytest

from spadscan.daemon.app import DeviceSession
from spadscan.daemon.arm import ur as ur_module
from spadscan.daemon.arm.rtde_child import Client
from spadscan.daemon.arm.rtde_link import RTDELink
from spadscan.daemon.arm.ur import URArm, _Reading
from spadscan.daemon.ursim.remote import SimURProcess
from spadscan.protocol.errors import DeviceError

_hosts = itertools.count(1)
WATCHDOG_HZ = 1.0  # a period the tests' own event loop keeps up with on a busy machine
POINTER = (0.0, 0.0, 0.1, 0.0, 0.0, 0.5)  # a TCP offset the pre-check refuses
DOWN = np.diag([1.0, -1.0, -1.0])


@pytest.fixture
def ur():
    """A simulated controller process on a fresh loopback address; motion runs 10x faster than real."""
    for _ in range(10):
        try:
            sim = SimURProcess(f"127.81.{os.getpid() % 250}.{next(_hosts) % 240 + 1}", time_scale=0.1)
            break
        except DeviceError:  # address in use: take the next one
            continue
    else:
        raise AssertionError("no free loopback address for the simulated controller")
    yield sim
    sim.close()


def make_arm(host: str, **kw) -> URArm:
    return URArm(host, **{"frequency": 100.0, "stale_after_s": 1.0, "timeout_s": 20.0, "watchdog_hz": WATCHDOG_HZ,
                          **kw})


def pose(x: float, y: float, z: float) -> np.ndarray:
    p = np.eye(4)
    p[:3, :3], p[:3, 3] = DOWN, (x, y, z)
    return p


async def until(pred, what: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.02)


async def until_arm_reads(arm: URArm, stop: str | None) -> None:
    """Until the arm's own reading shows safety stop `stop` (None: none): the receive stream comes at its own pace."""
    deadline = time.monotonic() + 30
    while (await arm.state()).safety_stop != stop:
        assert time.monotonic() < deadline, f"the arm never read safety stop {stop}"
        await asyncio.sleep(0.01)


def test_an_orderly_close_stops_the_control_script(ur, arun):
    """After a session that moved the arm, close() ends the program with the script's stop command: nothing is left
    running for the watchdog to stop, and the stop is no move."""
    async def run():
        arm = make_arm(ur.host)
        try:
            await arm.connect()
            await arm.prepare()
            await arm.move_to(pose(0.35, 0.0, 0.3), 0.5, 2.0)
        finally:
            await arm.close()
        return ur.state()

    state = arun(run())
    assert state["runtime_state"] == 1 and state["script_stops"] == 1 and state["watchdog_stops"] == 0
    assert [m.name for m in ur.moves] == ["moveL"]


def test_a_failed_pre_check_still_stops_the_control_script(ur, arun):
    """The rig does not start (the pre-check refuses a TCP offset): the session that connected is closed, and its
    program stopped, before the error comes back."""
    ur.configure(tcp_offset=POINTER)

    async def run():
        arm = make_arm(ur.host)
        with pytest.raises(DeviceError, match="rig did not start: .*active TCP offset"):
            async with DeviceSession([arm]):
                pass
        return ur.state()

    state = arun(run())
    assert state["runtime_state"] == 1 and state["script_stops"] == 1 and state["watchdog_stops"] == 0
    assert [m.name for m in ur.moves] == ["stopL"]  # the session's release; nothing moved


def test_the_watchdog_is_armed_at_connect_kept_while_waiting_and_stops_the_script_of_a_killed_client(ur, arun):
    """Connected, not yet prepared (the daemon waits for the sensor, or between scans): the watchdog is armed and
    kicked, so waiting several periods stops nothing. Then the ur_rtde process is killed, which no stopScript can
    follow: the watchdog stops the program within its period."""
    async def run():
        arm = make_arm(ur.host)
        try:
            await arm.connect()
            assert ur.state()["watchdog_period_s"] == 1.0 / WATCHDOG_HZ, "no watchdog armed at connect"
            await asyncio.sleep(3.0 / WATCHDOG_HZ)  # the point: time without a command of the daemon's own
            waited = ur.state()
            os.kill(arm._link.pid, signal.SIGKILL)
            await until(lambda: ur.state()["runtime_state"] == 1, "the watchdog to stop the program")
            stopped = ur.state()
        finally:
            await arm.close()
        return waited, stopped

    waited, stopped = arun(run())
    assert waited["runtime_state"] == 2 and waited["watchdog_stops"] == 0
    assert stopped["watchdog_stops"] == 1 and stopped["script_stops"] == 0


def test_a_safeguard_stop_at_connect_leaves_arming_the_watchdog_to_prepare(ur, arun):
    """A script held by a safeguard stop takes no command (ur_rtde would wait minutes for setWatchdog's answer):
    connecting does not ask, and prepare arms the watchdog once the stop is reset."""
    ur.safeguard_stop()

    async def run():
        arm = make_arm(ur.host)
        try:
            await arm.connect()
            at_connect = ur.state()["watchdog_period_s"]
            ur.clear_safeguard_stop()
            await until_arm_reads(arm, None)
            await arm.prepare()
            return at_connect, ur.state()["watchdog_period_s"]
        finally:
            await arm.close()

    assert arun(run()) == (None, 1.0 / WATCHDOG_HZ)


def test_a_close_during_a_safeguard_stop_leaves_the_script_to_the_watchdog(ur, arun, caplog):
    """The script takes no stop command while a safety stop holds it (ur_rtde would wait minutes for the program to
    end): close() does not ask, says so, finishes at once, and the watchdog armed at connect stops the program."""
    caplog.set_level(logging.WARNING, logger="spadscan.daemon")

    async def run():
        arm = make_arm(ur.host)
        try:
            await arm.connect()
            ur.safeguard_stop()
            await until_arm_reads(arm, "safeguard stop")
        finally:
            t0 = time.monotonic()
            await arm.close()
            took = time.monotonic() - t0
        await until(lambda: ur.state()["runtime_state"] == 1, "the watchdog to stop the program")
        return took, arm.timeout_s, ur.state()

    took, timeout_s, state = arun(run())
    assert took < timeout_s  # a stopScript waiting for the held script would be ended only at timeout_s
    assert state["watchdog_stops"] == 1 and state["script_stops"] == 0
    said = [r.getMessage() for r in caplog.records if "control script" in r.getMessage()]
    assert len(said) == 1 and re.search(r"the control script was left running \(safeguard stop holds it\); the "
                                        r"controller's watchdog stops it within 1 s$", said[0]), said


def test_a_close_under_a_safeguard_stop_held_since_connect_does_not_wait_and_says_what_to_do(ur, arun, caplog):
    """No watchdog could be armed (the stop held the script since connect) and no stop command be taken: ur_rtde's
    stopScript would wait 300 s for the program to end. close() does not send it, finishes at once and says that the
    program runs on, to be stopped on the pendant."""
    caplog.set_level(logging.WARNING, logger="spadscan.daemon")
    ur.safeguard_stop()

    async def run():
        arm = make_arm(ur.host, timeout_s=10.0)
        try:
            await arm.connect()
            await until_arm_reads(arm, "safeguard stop")
        finally:
            t0 = time.monotonic()
            await arm.close()
            took = time.monotonic() - t0
        return took, arm.timeout_s, ur.state()

    took, timeout_s, state = arun(run())
    assert took < timeout_s
    assert state["runtime_state"] == 2 and state["watchdog_period_s"] is None and state["script_stops"] == 0
    said = [r.getMessage() for r in caplog.records if "control script" in r.getMessage()]
    assert len(said) == 1 and said[0].endswith("no watchdog was armed on it: stop it on the teach pendant"), said


def test_the_client_process_stops_the_script_when_its_requests_end(ur, arun):
    """The ur_rtde process itself stops the script before it disconnects when its stdin closes (the daemon's close,
    or the daemon gone): disconnect() alone would leave the program running."""
    async def run():
        link = RTDELink("test link")
        await link.start()
        try:
            opened = await link.call("connect", 35.0, "open", ur.host, 100.0, None)
            running = ur.state()["runtime_state"]
        finally:
            await link.stop(20.0)
        return opened, running, ur.state()

    opened, running, state = arun(run())
    assert opened["watchdog"] is False and running == 2  # no watchdog asked for: only the stop ends the program
    assert state["runtime_state"] == 1 and state["script_stops"] == 1 and state["watchdog_stops"] == 0


def test_the_watchdog_armed_at_connect_runs_at_the_configured_rate(ur, arun):
    """[arm] watchdog_hz, 2 Hz by default (the backend's default, not this file's)."""
    async def run():
        arm = make_arm(ur.host, watchdog_hz=2.0)
        try:
            await arm.connect()
            return ur.state()["watchdog_period_s"]
        finally:
            await arm.close()

    assert arun(run()) == 0.5


# ---- one test of "held" for the daemon and its ur_rtde process ------------------------------------------------------
class Receive:
    """ur_rtde's receive interface as the ur_rtde process reads it: isProtectiveStopped and isEmergencyStopped are
    bits 2 and 7 of the safety status bits (RTDE guide), the safety mode as the controller reports it."""

    def __init__(self, mode: int, bits: int):
        self.mode, self.bits = mode, bits

    def isProtectiveStopped(self):
        return bool(self.bits & 1 << 2)

    def isEmergencyStopped(self):
        return bool(self.bits & 1 << 7)

    def getSafetyMode(self):
        return self.mode

    def getSafetyStatusBits(self):
        return self.bits

    def getRuntimeState(self):
        return 2  # PLAYING: a safeguard stop holds the program without pausing it

    def disconnect(self):
        pass


class Control:
    """ur_rtde's control interface with its program running; records the stopScript calls."""

    def __init__(self):
        self.stop_scripts = 0

    def isProgramRunning(self):
        return self.stop_scripts == 0

    def stopScript(self):
        self.stop_scripts += 1

    def disconnect(self):
        pass


def client(mode: int, bits: int) -> Client:
    c = Client()
    c.control, c.receive = Control(), Receive(mode, bits)
    return c


def daemon_reading(mode: int, bits: int) -> _Reading:
    return _Reading(np.zeros(6), np.zeros(6), 1.0, bool(bits & 1 << 2), bool(bits & 1 << 7), mode, True, np.zeros(6),
                    safety_bits=bits)


STATUS_BITS = [0, 1 << 0, 1 << 2, 1 << 4, (1 << 6) | (1 << 7), 1 << 8, 1 << 9, 1 << 10, (1 << 4) | (1 << 10)]
"""Safety status bits: normal, protective, safeguard, robot emergency, violation, fault, 'stopped due to safety'."""


@pytest.mark.parametrize("mode", range(1, 14))
def test_the_ur_rtde_process_judges_a_held_arm_as_the_daemon_does(mode):
    """Both decide with one predicate: for every safety mode and status bits, the ur_rtde process declines a command
    exactly where the daemon's reading says a stop holds the arm."""
    for bits in STATUS_BITS:
        held = client(mode, bits)._held()
        stop = daemon_reading(mode, bits).stop
        assert (held is not None) == (stop is not None), (mode, bits, held, stop)
        assert stop is None or stop in held


@pytest.mark.parametrize("mode", [12, 13])
def test_the_ur_rtde_process_sends_no_stop_script_in_a_safeguard_mode_the_daemon_declined(mode):
    """Safety modes 12 (automatic mode safeguard stop) and 13 (three position enabling stop) hold the arm for the
    daemon whatever the status bits say; the ur_rtde process must not send stopScript there either (ur_rtde would
    wait for the program to end until the daemon kills the process), neither when asked nor at its own close."""
    assert daemon_reading(mode, 1 << 10).stop == "safeguard stop"
    c = client(mode, 1 << 10)
    assert c.stop_script() == {"stopped": False,
                               "why": f"the arm is stopped for safety (safeguard stop, safety mode {mode})"}
    control = c.control
    c.close()
    assert control.stop_scripts == 0


# ---- the close's messages and the watchdog flag ---------------------------------------------------------------------
def test_a_close_over_a_stale_link_names_the_arm_once(ur, arun, caplog):
    """The reason the script could not be stopped comes from the arm's own error, which names the arm too: the
    warning says the name once."""
    caplog.set_level(logging.WARNING, logger="spadscan.daemon")

    async def run():
        arm = make_arm(ur.host)
        try:
            await arm.connect()
            ur.drop_link("freeze")  # the stream repeats its last package: stale data
            await asyncio.sleep(0.2)
            await arm.state()  # the arm has seen the last package: the close's wait for a newer one goes stale
        finally:
            await arm.close()
            ur.restore_link()
        return arm.name

    name = arun(run())
    said = [r.getMessage() for r in caplog.records if "could not stop the control script" in r.getMessage()]
    assert len(said) == 1 and said[0].count(name) == 1, said
    assert said[0].startswith(f"{name}: could not stop the control script (receive data stale: ")


class ReconnectingArm(URArm):
    """A UR arm whose controller shows the control script stopped under a safeguard stop that outlasts the wait in
    clear_fault; reuploadScript does not start it, so clear_fault reconnects, and the new ur_rtde process arms the
    new program's watchdog as it connects (`opened`)."""

    def __init__(self, opened_watchdog: bool):
        super().__init__("127.0.0.1", watchdog_hz=2.0)
        self._open, self.opened_watchdog, self.calls = True, opened_watchdog, []

    async def _fresh(self, what):
        return _Reading(np.zeros(6), np.zeros(6), 1.0, False, False, 5, True, np.zeros(6), safety_bits=1 << 4,
                        program_running=False)

    async def _call(self, what, op, *args, timeout_s=None):
        self.calls.append(op)
        return True

    async def _script_started(self):
        return False

    async def reconnect(self):
        self.calls.append("reconnect")
        self._watchdog_set, self._tcp_checked = self.opened_watchdog, False


@pytest.mark.parametrize("armed", [True, False])
def test_clear_fault_keeps_the_watchdog_flag_the_reconnect_set(arun, monkeypatch, armed):
    """After the fallback reconnect the flag says what the new ur_rtde process did: a close must not warn "no
    watchdog was armed" over a watchdog that is armed (nor claim one that is not)."""
    monkeypatch.setattr(ur_module, "CLEARED_WITHIN_S", 0.05)
    arm = ReconnectingArm(armed)
    arun(arm.clear_fault())
    assert arm.calls == ["reupload", "reconnect"] and arm._watchdog_set is armed


def test_a_close_ends_a_program_a_protective_stop_paused_with_the_dashboards_stop(ur, arun, caplog):
    """UR: a protective stop only pauses the program, and a paused program takes no script command (stopScript
    cannot reach it); Play on the pendant would finish its halted move after the daemon let go. close() ends it with
    the dashboard's `stop`, and says so."""
    caplog.set_level(logging.INFO, logger="spadscan.daemon")

    async def run():
        arm = make_arm(ur.host)
        try:
            await arm.connect()
            await arm.prepare()
            ur.protective_stop()
            await until_arm_reads(arm, "protective stop")
            ur.clear_protective_stop()
            await until_arm_reads(arm, None)
            paused = ur.state()
        finally:
            await arm.close()
        return paused, ur.state(), arm.name

    paused, closed, name = arun(run())
    assert paused["runtime_state"] == 4
    assert closed["runtime_state"] == 1 and closed["dashboard_stops"] == 1 and closed["script_stops"] == 0
    assert "stop" in ur.dashboard_log()
    said = [r.getMessage() for r in caplog.records if "control script" in r.getMessage()]
    assert said == [f"{name}: the paused control script was stopped (the dashboard's stop)"], said


def test_the_client_process_ends_a_paused_program_when_its_requests_end(ur, arun):
    """The ur_rtde process's own close (the parent gone) ends a paused program the same way."""
    async def run():
        link = RTDELink("test link")
        await link.start()
        try:
            await link.call("connect", 35.0, "open", ur.host, 100.0, None)
            ur.protective_stop()
            deadline = time.monotonic() + 30  # until the process's own reading shows it (the stream's own pace)
            while not (await link.call("read", 20.0, "read"))["paused"]:
                assert time.monotonic() < deadline, "the ur_rtde process never read the program paused"
                await asyncio.sleep(0.01)
        finally:
            await link.stop(20.0)
        return ur.state()

    state = arun(run())
    assert state["runtime_state"] == 1 and state["dashboard_stops"] == 1
