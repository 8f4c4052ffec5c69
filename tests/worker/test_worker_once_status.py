"""`spadscan worker --once` run as a script runs it: its last line names each scan it left unqueued and why, and its
exit status tells "nothing run, scans left waiting" (75) from a run that did work or had nothing to do (0)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

from spadscan.commands.worker import LEFT_WAITING
from spadscan.worker.queue import Queue

from test_watcher import complete_source, make_scan


def once(root) -> subprocess.CompletedProcess:
    """`spadscan worker --root ROOT --once`, as a script would run it."""
    cmd = [sys.executable, "-m", "spadscan.cli", "worker", "--root", str(root), "--once", "--poll-s", "0.05"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def copy_under_way(root, name: str) -> None:
    """A complete capture copied in so far (its last chunk not yet there), its files written a day from now (a clock
    ahead of this one): it stays a copy still under way however long the test takes."""
    complete_source(root / name, 4)
    shutil.rmtree(sorted((root / name).glob("chunk-*"))[-1])
    later = time.time() + 86400
    for path in [root / name, *(root / name).rglob("*")]:
        os.utime(path, (later, later))


def last_line(done: subprocess.CompletedProcess) -> str:
    lines = done.stdout.strip().splitlines()
    assert lines, done
    return lines[-1]


def test_once_that_leaves_every_scan_names_them_and_exits_75(tmp_path):
    make_scan(tmp_path, "rec", "running")
    copy_under_way(tmp_path, "copy")
    done = once(tmp_path)
    assert done.returncode == LEFT_WAITING == 75, done
    line = last_line(done)
    assert line.startswith("spadscan worker: 0 done, 0 failed; left 2 scans not queued yet: "), line
    assert "rec (still being recorded)" in line, line
    assert "copy (a copy still under way: taken once nothing in it has changed for 60 s, in " in line, line
    assert Queue.for_root(tmp_path).counts()["queued"] == 0


def test_once_with_nothing_to_do_exits_0_and_names_nothing(tmp_path):
    make_scan(tmp_path, "gone", "aborted")  # never taken: not waiting
    done = once(tmp_path)
    assert done.returncode == 0, done
    assert last_line(done) == "spadscan worker: 0 done, 0 failed", done


def test_once_that_settled_a_job_exits_0_and_still_names_what_it_left(tmp_path):
    make_scan(tmp_path, "a")
    kept = tmp_path / "a" / "recon" / "a-fast"
    kept.mkdir(parents=True)
    (kept / "mesh.ply").write_text("a result already there: the job is kept, not run")
    make_scan(tmp_path, "rec", "running")
    done = once(tmp_path)
    assert done.returncode == 0, done
    assert last_line(done) == ("spadscan worker: 0 done, 0 failed, 1 not run (their results were already there); "
                               "left 1 scan not queued yet: rec (still being recorded)"), done


def test_once_leaves_a_queued_job_it_may_not_take_names_it_and_ends(tmp_path, monkeypatch, capsys):
    """Another user's job on a shared queue (its file's utime refused: EACCES) stayed queued, and --once, which ran
    until nothing was queued, waited on it for good. It ends once nothing else is left, naming that job and why; the
    job stays queued for a worker that may take it."""
    from spadscan.cli import main

    make_scan(tmp_path, "mine")
    kept = tmp_path / "mine" / "recon" / "mine-fast"
    kept.mkdir(parents=True)
    (kept / "mesh.ply").write_text("a result already there: the job is kept, not run")
    make_scan(tmp_path, "theirs")
    real = os.utime

    def utime(path, *args, **kwargs):
        if str(path).endswith("queued/theirs-fast.json"):
            raise PermissionError(13, "Permission denied", str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(os, "utime", utime)
    assert main(["worker", "--root", str(tmp_path), "--once", "--poll-s", "0.05"]) == 0
    queued = tmp_path / ".queue" / "queued" / "theirs-fast.json"
    assert capsys.readouterr().out.strip().splitlines()[-1] == (
        "spadscan worker: 0 done, 0 failed, 1 not run (their results were already there); left 1 queued job it may "
        f"not take, for a worker that may: theirs-fast ([Errno 13] Permission denied: '{queued}')")
    assert Queue.for_root(tmp_path).queued_ids() == {"theirs-fast"}
    # with nothing else to run it says the same, exit status 75 (run again later)
    shutil.rmtree(tmp_path / "mine")
    assert main(["worker", "--root", str(tmp_path), "--once", "--poll-s", "0.05"]) == LEFT_WAITING
    assert capsys.readouterr().out.strip().splitlines()[-1] == (
        "spadscan worker: 0 done, 0 failed; left 1 queued job it may not take, for a worker that may: theirs-fast "
        f"([Errno 13] Permission denied: '{queued}')")
