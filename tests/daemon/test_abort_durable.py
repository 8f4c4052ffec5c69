"""An abort the disk cannot take (full, read-only) is never undone by a restart: the reply says it is not recorded
yet, `abort-pending.json` keeps it where an empty file still fits (no daemon takes such a scan over, even with
auto_resume), and the daemon writes scan.json again until it lands: every ABORT_RETRY_S, at each request and at
shutdown. Nothing published is lost meanwhile."""

from __future__ import annotations

import errno
import os

import pytest

from spadscan.daemon import abort_book, scan_job
from spadscan.daemon.scan_job import ABORT_PENDING
from spadscan.protocol.capture_format import read_json
from spadscan.protocol.errors import ConfigError

from test_runner import daemon_runner, make_cfg, until, sphere  # noqa: F401  (sphere: the fixture)


@pytest.fixture
def disk(monkeypatch):
    """The captures' disk: `disk["error"]` set to an errno makes every chunk and manifest write fail with it (a
    full disk: ENOSPC; a disk remounted read-only: EROFS); None lets them through. An empty file (abort-pending.json)
    still fits on a full disk, as on a real one."""
    import spadscan.protocol.capture_writer as cw

    state = {"error": None}
    real_json, real_npy = cw.write_json_atomic, cw.save_npy_durable

    def guarded(real):
        def write(path, data):
            if state["error"] is not None:
                raise OSError(state["error"], "No space left on device" if state["error"] == errno.ENOSPC else
                              "Read-only file system", str(path))
            real(path, data)
        return write

    monkeypatch.setattr(cw, "write_json_atomic", guarded(real_json))
    monkeypatch.setattr(cw, "save_npy_durable", guarded(real_npy))
    return state


def manifest(folder) -> dict:
    return read_json(folder / "scan.json")


async def abort_on_a_full_disk(cfg, sphere, disk, name: str) -> dict:  # noqa: F811
    """A daemon starts scan `name`; the disk fills up (the scan pauses), the operator aborts it, and the daemon is
    stopped with the disk still full. Returns the abort's reply."""
    async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
        await runner.start(name)
        await until(lambda: runner.job.next_pose >= 3, "three poses")
        disk["error"] = errno.ENOSPC
        await until(lambda: runner.state == "paused", "the pause for the full disk")
        return await runner.abort()


async def restarted(cfg, sphere, meanwhile=None, wait: str | None = None) -> dict:  # noqa: F811
    """A daemon started on cfg's captures root: its status once it has recovered; `meanwhile()` then runs (room is
    made) and a `status` request follows, whose reply is returned too (as {"first", "then"}). `wait`: a scan name
    whose `wait` is refused, its error returned as "waited"."""
    async with daemon_runner(cfg, sphere) as runner:
        await runner.recover()
        first = runner.status()
        if wait is not None:
            with pytest.raises(ConfigError) as refused:
                await runner.wait(wait)
            return {"first": first, "waited": str(refused.value)}
        if meanwhile is None:
            return {"first": first}
        meanwhile()
        await runner.aborts.retry()  # what the Dispatcher runs before each request
        return {"first": first, "then": runner.status()}


def test_an_abort_the_full_disk_cannot_take_is_not_undone_by_a_restart(arun, tmp_path, sphere, disk):  # noqa: F811
    cfg = make_cfg(tmp_path, views=10, auto_resume=True)
    folder = tmp_path / "caps" / "s1"
    reply = arun(abort_on_a_full_disk(cfg, sphere, disk, "s1"))
    # The reply is true: the scan is over in the daemon, and it says that the capture does not record it yet.
    assert reply["aborted"] == "s1" and reply["abort_recorded"] is False and reply["state"] == "idle", reply
    said = reply["last_error"]
    assert said.startswith("scan 's1' is aborted, but its scan.json does not say so yet (disk full while "), said
    assert f"{ABORT_PENDING} in the scan folder keeps it" in said, said
    assert reply["unrecorded_aborts"]["s1"]["kept_on_disk"] is True
    assert manifest(folder)["state"] == "running" and (folder / ABORT_PENDING).is_file()
    published = {p.relative_to(folder): p.read_bytes() for p in folder.glob("chunk-*/*")}

    # Restarted (systemd, a reboot) with the disk still full: the scan is not taken over, the arm does not move; and
    # `ctl wait s1` says the abort is not recorded yet (not "no scan named").
    status = arun(restarted(cfg, sphere, wait="s1"))
    waited, status = status["waited"], status["first"]
    assert status["state"] == "idle" and status["scan"] is None, status
    assert "s1" in status["unrecorded_aborts"] and manifest(folder)["state"] == "running"
    assert waited.startswith("scan 's1' is aborted, but its scan.json does not say so yet (disk full while "), waited
    assert f"{ABORT_PENDING} in the scan folder keeps it" in waited, waited

    # Restarted again; room is made: the next request records the abort, and the file that kept it goes.
    seen = arun(restarted(cfg, sphere, meanwhile=lambda: disk.update(error=None)))
    assert seen["first"]["state"] == "idle" and seen["first"]["scan"] is None, seen
    assert "unrecorded_aborts" not in seen["then"] and seen["then"]["last_error"] is None, seen["then"]
    m = manifest(folder)
    assert m["state"] == "aborted" and m["reason"] == "aborted by user" and "paused" not in m
    assert not (folder / ABORT_PENDING).exists()
    assert {p.relative_to(folder): p.read_bytes() for p in folder.glob("chunk-*/*")} == published
    assert arun(restarted(cfg, sphere))["first"]["state"] == "idle"


def test_the_daemon_writes_the_abort_again_by_itself_once_room_comes_back(arun, tmp_path, sphere, disk,  # noqa: F811
                                                                          monkeypatch):
    monkeypatch.setattr(abort_book, "ABORT_RETRY_S", 0.01)
    cfg = make_cfg(tmp_path, views=10)
    folder = tmp_path / "caps" / "s2"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("s2")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            disk["error"] = errno.ENOSPC
            await until(lambda: runner.state == "paused", "the pause")
            reply = await runner.abort(reason="wrong object")
            disk["error"] = None
            await until(lambda: manifest(folder)["state"] == "aborted", "the abort on disk")
            await until(lambda: not runner.aborts.unrecorded, "the abort counted as recorded")
            return reply, runner.status()

    reply, status = arun(scenario())
    assert reply["abort_recorded"] is False and "written again every 0.01 s" in reply["last_error"], reply
    assert status["last_error"] is None and "unrecorded_aborts" not in status
    assert manifest(folder)["reason"] == "wrong object" and not (folder / ABORT_PENDING).exists()


REASON = "test full / 100% über, twice: ok?"  # a '/' and a '%' must not escape or corrupt a file name


@pytest.fixture
def no_room_for_records(disk, monkeypatch):
    """A disk so full that abort-pending.json's record does not fit either while `disk["error"]` is set (the file
    itself, and a name, still do); `no_room_for_records["records"] = True` makes room for records alone."""
    state = {"records": False}

    class FullDisk:
        """The os module as scan_job sees it, its writes into files refused while the disk is full."""

        def __getattr__(self, name):
            return getattr(os, name)

        @staticmethod
        def write(fd, data):
            if disk["error"] is not None and not state["records"]:
                raise OSError(errno.ENOSPC, "No space left on device")
            return os.write(fd, data)

    monkeypatch.setattr(scan_job, "os", FullDisk())
    return state


def test_the_operators_reason_survives_a_restart_on_a_disk_too_full_for_its_record(arun, tmp_path, sphere, disk,
                                                                                      no_room_for_records):  # noqa: F811
    cfg = make_cfg(tmp_path, views=10)
    folder = tmp_path / "caps" / "s3"

    async def aborted():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("s3")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            disk["error"] = errno.ENOSPC
            await until(lambda: runner.state == "paused", "the pause for the full disk")
            return await runner.abort(reason=REASON)

    reply = arun(aborted())
    assert reply["abort_recorded"] is False and (folder / ABORT_PENDING).read_bytes() == b""
    # Restarted with the disk still full: the reason it holds is the operator's, and so is the one recorded later.
    status = arun(restarted(cfg, sphere))["first"]
    assert status["unrecorded_aborts"]["s3"]["reason"] == REASON, status
    arun(restarted(cfg, sphere, meanwhile=lambda: disk.update(error=None)))
    m = manifest(folder)
    assert m["state"] == "aborted" and m["reason"] == REASON, m
    assert sorted(p.name for p in folder.iterdir() if "abort" in p.name) == []  # the marker and the name: gone


def test_an_empty_abort_pending_file_gets_its_record_once_there_is_room_for_it(arun, tmp_path, sphere, disk,
                                                                              no_room_for_records):  # noqa: F811
    cfg = make_cfg(tmp_path, views=10)
    folder = tmp_path / "caps" / "s4"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("s4")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            disk["error"] = errno.ENOSPC
            await until(lambda: runner.state == "paused", "the pause for the full disk")
            await runner.abort(reason=REASON)
            before = (folder / ABORT_PENDING).read_bytes()
            no_room_for_records["records"] = True  # room for a small file, not yet for scan.json
            await runner.aborts.retry()
            return before, runner.status()

    before, status = arun(scenario())
    assert before == b"" and status["unrecorded_aborts"]["s4"]["kept_on_disk"] is True
    assert read_json(folder / ABORT_PENDING)["reason"] == REASON and manifest(folder)["state"] == "running"


def test_an_abort_a_read_only_disk_cannot_keep_says_so_and_lands_at_shutdown(arun, tmp_path, sphere, disk,  # noqa: F811
                                                                             monkeypatch):
    """Read-only: not even abort-pending.json can be made. The reply says that nothing on disk keeps the abort and
    what a restart would do; the daemon tries once more as it stops (here the disk is writable again by then)."""
    monkeypatch.setattr(abort_book, "ABORT_RETRY_S", 3600.0)  # only the shutdown's try may land it
    monkeypatch.setattr(abort_book, "note_abort_pending", lambda path, reason: False)
    cfg = make_cfg(tmp_path, views=10, auto_resume=True)
    folder = tmp_path / "caps" / "ro"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("ro")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            disk["error"] = errno.EROFS
            await until(lambda: runner.state == "paused", "the pause")
            reply = await runner.abort()
            disk["error"] = None
            return reply, manifest(folder)["state"]

    reply, before_shutdown = arun(scenario())
    said = reply["last_error"]
    assert reply["abort_recorded"] is False and "write error while recording it: Read-only file system" in said
    assert "nothing on disk keeps it" in said and "scans on by itself (auto_resume)" in said, said
    assert "make room or make the disk writable before stopping this daemon" in said, said
    assert before_shutdown == "running" and manifest(folder)["state"] == "aborted"


def test_ctl_abort_exits_1_when_the_abort_is_not_recorded_yet(tmp_path, monkeypatch, capsys):
    import spadscan.daemon.client as client
    from spadscan.cli import main

    asked = []
    said = "scan 's1' is aborted, but its scan.json does not say so yet (disk full while recording it)"
    monkeypatch.setattr(client, "call", lambda path, op, timeout, **request: asked.append((op, request)) or
                        {"ok": True, "state": "idle", "aborted": "s1", "abort_recorded": False, "last_error": said})
    assert main(["ctl", "--socket", str(tmp_path / "ctl.sock"), "abort", "--reason", "dropped"]) == 1
    out, err = capsys.readouterr()
    assert out == "scan 's1' aborted (not recorded on disk yet)\n" and err == f"spadscan: error: {said}\n"
    assert asked == [("abort", {"reason": "dropped"})]


def test_an_empty_abort_pending_file_still_keeps_the_abort_once_the_disk_is_read_only(tmp_path, monkeypatch):
    """A retry finds the disk read-only: the empty abort-pending.json made while it was full still keeps the abort
    (no daemon takes the scan over), so the operator is not told that a restart would."""
    from spadscan.daemon import scan_job

    (tmp_path / ABORT_PENDING).write_bytes(b"")  # made on the full disk, with no room for its record
    real_open = scan_job.os.open

    def read_only(path, *args, **kwargs):
        if str(path).endswith(ABORT_PENDING):
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(scan_job.os, "open", read_only)
    assert scan_job.note_abort_pending(tmp_path, "enough") is True
    monkeypatch.setattr(scan_job.os, "open", real_open)
    (tmp_path / ABORT_PENDING).unlink()
    monkeypatch.setattr(scan_job.os, "open", read_only)
    assert scan_job.note_abort_pending(tmp_path, "enough") is False  # nothing there to keep it
