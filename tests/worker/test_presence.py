"""A running worker keeps a presence file under its queue (presence.py), idle or not, and removes it when it stops; a
file counts only while it is renewed and its process exists, so a killed worker is not taken for a running one."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace

from spadscan.cli import main as cli_main
from spadscan.worker.holder import Holder
from spadscan.worker.jobs import Job
from spadscan.worker.pool import Worker
from spadscan.worker.presence import (FORGET_S, MISSED_RENEWALS, RENEW_S, Presence, present_workers,
                                      presence_path, remove_presence, start_command, write_presence)
from spadscan.worker.queue import Queue
from spadscan.worker.worker_config import WorkerConfig

from test_reclaim_note import dead_holder


def presence(holder: Holder, **changes) -> Presence:
    return replace(Presence(holder.to_dict(), "/captures", 1000.0, 1), **changes)


def aged(path, seconds: float) -> float:
    """`path` last written `seconds` before now; returns now (the reading's clock)."""
    now = time.time()
    os.utime(path, (now - seconds, now - seconds))
    return now


def test_a_renewed_file_of_a_live_process_is_listed(tmp_path):
    write_presence(tmp_path, presence(Holder.current(), running=["s-fast"], processes=2))
    [row] = present_workers(tmp_path)
    assert (row["pid"], row["root"], row["processes"], row["running"]) == (os.getpid(), "/captures", 2, ["s-fast"])
    assert row["seen_s"] < RENEW_S


def test_a_file_no_longer_renewed_does_not_count(tmp_path):
    path = write_presence(tmp_path, presence(Holder.current()))
    now = aged(path, MISSED_RENEWALS * RENEW_S - 5)
    assert len(present_workers(tmp_path, now)) == 1
    now = aged(path, MISSED_RENEWALS * RENEW_S + 5)
    assert present_workers(tmp_path, now, tidy=True) == []
    assert path.exists()  # its worker may be on another machine, with the queue's mount lost for a while
    now = aged(path, FORGET_S + 5)  # a day: whatever became of it, it is forgotten
    assert present_workers(tmp_path, now, tidy=True) == [] and not path.exists()


def test_a_dead_workers_file_does_not_count_and_is_tidied_away(tmp_path):
    path = write_presence(tmp_path, presence(dead_holder()))
    leftover = path.with_name(f".{path.name}.1-00000000.tmp")  # a write killed half way
    leftover.write_text("{")
    assert present_workers(tmp_path) == [] and path.exists()
    assert present_workers(tmp_path, tidy=True) == []
    assert not path.exists() and leftover.exists()
    now = aged(leftover, FORGET_S + 5)
    present_workers(tmp_path, now, tidy=True)
    assert not leftover.exists()


def test_files_that_go_while_they_are_listed_leave_the_others_listed(tmp_path):
    """Another worker's tidy or rename removes a file between the listing and its reading (a dangling link stands
    for it): the workers whose files stay are listed all the same."""
    path = write_presence(tmp_path, presence(Holder.current()))
    (path.parent / ".gone.json.1-00000000.tmp").symlink_to(tmp_path / "removed")
    (path.parent / "gone.json").symlink_to(tmp_path / "removed")
    [row] = present_workers(tmp_path, tidy=True)
    assert row["pid"] == os.getpid()


def test_two_workers_with_one_host_name_and_pid_keep_a_file_each(tmp_path):
    """Two containers with one host name, both running the worker as pid 1: one's stop leaves the other listed."""
    me = Holder.current()
    first, second = presence(me), presence(replace(me, pid_ns="pid:[1]"))
    write_presence(tmp_path, first)
    write_presence(tmp_path, second)
    assert len(present_workers(tmp_path)) == 2
    remove_presence(tmp_path, first)
    assert len(present_workers(tmp_path)) == 1


def test_damaged_files_and_no_folder_list_no_worker(tmp_path):
    assert present_workers(tmp_path) == []
    path = presence_path(tmp_path, presence(Holder.current()))
    path.parent.mkdir()
    path.write_text("{not json")
    (path.parent / "other.json").write_text(json.dumps({"holder": {"pid": 1}}))
    me = Holder.current().to_dict()
    (path.parent / "a-string-pid.json").write_text(json.dumps({"holder": {**me, "pid": "x"}}))
    (path.parent / "a-list.json").write_text(json.dumps({"holder": ["vm", 1]}))
    assert present_workers(tmp_path, tidy=True) == []


def test_a_worker_is_present_while_it_runs_idle_and_gone_once_stopped(tmp_path, arun):
    root = tmp_path / "captures"
    root.mkdir()
    worker = Worker(WorkerConfig(root=root, poll_s=0.05, processes=2), log=lambda line: None)
    path = presence_path(worker.queue.path, worker.presence)
    stale = write_presence(worker.queue.path, presence(dead_holder()))  # a killed worker's, left behind

    async def run_until_present() -> list[dict]:
        stop = asyncio.Event()
        task = asyncio.create_task(worker.run(stop))
        deadline = time.monotonic() + 60
        while not path.exists() and not task.done() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        rows = present_workers(worker.queue.path)
        stop.set()
        await task
        return rows

    [row] = arun(run_until_present())
    assert (row["pid"], row["root"], row["processes"], row["running"]) == (os.getpid(), str(root.resolve()), 2, [])
    assert not path.exists(), "a stopped worker leaves its file behind"
    assert not stale.exists(), "a starting worker leaves a dead one's file"


def test_status_says_which_workers_run_and_how_to_start_one_when_none_does(tmp_path, capsys):
    queue = Queue.for_root(tmp_path)
    assert cli_main(["worker", "--root", str(tmp_path), "--status"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-1] == ("no worker is running on this queue (a worker queues and reconstructs each complete scan): "
                       f"{start_command(tmp_path, queue.path)}")
    me = Holder.current()
    write_presence(queue.path, presence(me, started_unix=0.0, running=["mug-fast"], once=True))
    queue.enqueue(Job(id="mug-fast", scan="mug"))
    assert cli_main(["worker", "--root", str(tmp_path), "--status"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-1] == f"worker: {me.host} pid {me.pid} (running mug-fast; since 1970-01-01 00:00 UTC, until drained)"
    damaged = presence(me, started_unix=1e300)  # a start no clock can name
    write_presence(queue.path, damaged)
    assert cli_main(["worker", "--root", str(tmp_path), "--status"]) == 0
    assert "(waiting for scans; since an unknown time)" in capsys.readouterr().out.splitlines()[-1]
    remove_presence(queue.path, damaged)
    other = Holder.of_pid(os.getppid())  # a second worker, idle, that started a minute later
    write_presence(queue.path, presence(other, started_unix=60.0))
    assert cli_main(["worker", "--root", str(tmp_path), "--status"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == (
        f"2 workers: {me.host} pid {me.pid} (running mug-fast; since 1970-01-01 00:00 UTC, until drained); "
        f"{other.host} pid {other.pid} (waiting for scans; since 1970-01-01 00:01 UTC)")


def test_the_command_that_starts_a_worker_names_a_queue_only_when_not_the_roots():
    assert start_command("/data/my scans", "/data/my scans/.queue") == "spadscan worker --root '/data/my scans'"
    assert start_command("/data/s", "/shared/q") == "spadscan worker --root /data/s --queue /shared/q"


def test_the_command_is_present_until_ctrl_c_which_ends_it_with_what_it_settled_and_status_0(tmp_path):
    """`spadscan worker` as a service: present while it waits; Ctrl-C (as `systemctl stop`'s SIGTERM) is a stop as
    asked, said in a last line, exit status 0, and its presence file is gone."""
    proc = subprocess.Popen([sys.executable, "-m", "spadscan.cli", "worker", "--root", str(tmp_path), "--poll-s",
                             "0.05"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        folder = tmp_path / ".queue" / "workers"
        deadline = time.monotonic() + 60
        while not list(folder.glob("*.json")) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        [row] = present_workers(tmp_path / ".queue")
        assert (row["pid"], row["running"]) == (proc.pid, [])
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert out.splitlines()[-1] == "spadscan worker: stopped; 0 done, 0 failed while it ran", out
    assert not list(folder.glob("*.json"))


def test_an_idle_worker_with_a_long_poll_still_renews_its_file_in_time(tmp_path, arun, monkeypatch):
    """A poll of a minute (`--poll-s 60 --lease-s 600`) must not leave the file older than its window between
    renewals: the loop wakes for each renewal (the renewal period made short here, as the poll is long)."""
    import spadscan.worker.pool as pool

    writes: list[float] = []
    monkeypatch.setattr(pool, "RENEW_S", 0.05)
    monkeypatch.setattr(pool, "write_presence", lambda queue, p: writes.append(time.monotonic()))
    root = tmp_path / "captures"
    root.mkdir()
    worker = Worker(WorkerConfig(root=root, poll_s=60, lease_s=600), log=lambda line: None)

    async def run_until_renewed() -> None:
        stop = asyncio.Event()
        task = asyncio.create_task(worker.run(stop))
        deadline = time.monotonic() + 30
        while len(writes) < 3 and not task.done() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        stop.set()
        await task

    arun(run_until_renewed())
    assert len(writes) >= 3, f"renewed {len(writes)} times in 30 s with a 60 s poll"
