"""A worker that waits for room on a full disk says so in its presence file (`room_wait`, read by the dashboard, `ctl`
and `worker --status`), rewritten when the wait begins and when it ends, not only at its next renewal."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

import spadscan.worker.pool as pool_module
from spadscan.cli import main as cli_main
from spadscan.worker.disk_room import RoomWait, mount_point
from spadscan.worker.holder import Holder
from spadscan.worker.pool import Worker
from spadscan.worker.presence import Presence, present_workers, presence_path, write_presence
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from test_worker_disk_full import JOB, PAGE, RECON, refused_until_room, run_worker, until

KEYS = {"mount", "folder", "free_bytes", "need_bytes", "since_unix", "retry_unix", "quota", "relative_to", "relative"}


def own_row(worker: Worker) -> dict:
    """The worker's row as readers of the queue see it ({} before its file is written)."""
    rows = [r for r in present_workers(worker.queue.path) if r["pid"] == worker.presence.holder["pid"]]
    return rows[0] if rows else {}


def a_wait(folder: Path) -> RoomWait:
    return RoomWait(Path(folder), mount_point(folder), PAGE, PAGE + (1 << 20), 600.0, 1_700_000_000.0)


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_worker_waiting_for_room_says_so_in_its_presence_file(tmp_path, monkeypatch, arun):
    full, _, root = refused_until_room(tmp_path, monkeypatch)
    monkeypatch.setattr(pool_module, "RENEW_S", 3600.0)  # no renewal in the test: only what changes rewrites it
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05, max_attempts=1, recon=RECON), log=lines.append)
    seen: list[dict | None] = []

    async def scenario():
        async def meanwhile():
            await until(lambda: own_row(worker).get("room_wait") is not None, "the wait in the presence file")
            seen.append(own_row(worker)["room_wait"])
            full.unlink()

        return (await run_worker(worker, meanwhile))[1]

    assert arun(scenario()) == {JOB: "done"}, lines
    (wait,) = seen
    room = worker.queue.records(JOB)[0]["room"]
    assert set(wait) == KEYS and wait == room, "the contract's keys exactly; the job's record says the same wait"
    assert (wait["mount"], wait["folder"]) == (str(mount_point(root)), str(root / "s" / "recon"))
    assert (wait["relative_to"], wait["relative"]) == ("root", "s/recon"), "found by a reader under its own root"
    assert wait["free_bytes"] == PAGE and wait["need_bytes"] > PAGE and wait["quota"] is False
    assert isinstance(wait["since_unix"], float) and wait["retry_unix"] == pytest.approx(wait["since_unix"] + 600.0)


def test_the_presence_file_is_rewritten_when_a_wait_begins_and_when_it_ends(tmp_path, monkeypatch):
    monkeypatch.setattr(pool_module, "RENEW_S", 3600.0)  # only a change rewrites the file now
    worker = Worker(WorkerConfig(root=tmp_path, poll_s=0.05, recon=RECON), log=lambda line: None)
    path = presence_path(worker.queue.path, worker.presence)
    worker._say_present()
    assert json.loads(path.read_text())["room_wait"] is None
    worker.room = a_wait(tmp_path)
    worker._say_present()
    assert json.loads(path.read_text())["room_wait"] == worker.room.note()
    worker.room = None
    worker._say_present()
    assert json.loads(path.read_text())["room_wait"] is None


def test_a_damaged_wait_in_a_presence_file_reads_as_none(tmp_path):
    presence = Presence(Holder.current().to_dict(), "/captures", time.time(), 1, room_wait={"mount": "/data"})
    write_presence(tmp_path, presence)
    assert present_workers(tmp_path)[0]["room_wait"] is None


def test_worker_status_says_which_worker_waits_for_room_where_and_until_when(tmp_path, capsys):
    root = tmp_path / "caps"
    Queue.for_root(root)
    wait = a_wait(root)
    until_text = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(wait.retry_unix))
    presence = Presence(Holder.current().to_dict(), str(root), time.time(), 1, room_wait=wait.note())
    write_presence(root / ".queue", presence)
    assert cli_main(["worker", "--root", str(root), "--status"]) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    assert (f"(waiting for scans; waiting for room on {wait.mount} before claiming a job, until {until_text} at the "
            f"latest; since ") in last, last
