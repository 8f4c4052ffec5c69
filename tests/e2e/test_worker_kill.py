"""kill -9 of a worker mid-job: two `spadscan worker` processes serve one captures root; the one
running a job is killed; the job finishes on the other worker and every scan is reconstructed exactly once (a real
reconstruction, two optimisation steps).

A job of two steps may end by finishing its work as soon as by noticing that its worker is gone: where these tests
wait for such a job to end, that orders what follows and proves nothing of the job's watch on its worker. That watch
is proven where the job cannot finish meanwhile: tests/worker/test_worker_process.py's killed worker (a stand-in job
that sleeps 60 s); `test_a_job_whose_worker_died_before_it_started_exits` here proves the check a job makes as it
starts (a worker already gone)."""

from __future__ import annotations

import json
import os
import shutil
import signal
from pathlib import Path

import pytest

from e2e_helpers import drop_ground_truth, processes_mentioning, spadscan, spadscan_argv, wait_for
from spadscan.worker.queue import Queue

SCANS = ("s0", "s1")


def parent_pid(pid: int) -> int | None:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return None


def threads(pid: int) -> int:
    """Threads of a live process (0 when it is gone). A job process starts its parent watch as its second thread."""
    try:
        return len(os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return 0


def job_processes(root: Path) -> dict[int, str]:
    """Job child processes (`python -m spadscan.worker.jobs`) working on scans under `root`."""
    return {pid: cmd for pid, cmd in processes_mentioning(str(root)).items() if "spadscan.worker.jobs" in cmd}


def make_captures(root: Path) -> None:
    root.mkdir()
    r = spadscan("simulate", "builtin:sphere", "--out", root / SCANS[0], "--views", 6, "--rays-per-zone", 16,
                 "--sensor", "tmf8820", "--no-progress")
    assert r.returncode == 0, r.stderr
    drop_ground_truth(root / SCANS[0])
    for name in SCANS[1:]:
        shutil.copytree(root / SCANS[0], root / name)


@pytest.mark.slow
def test_a_killed_workers_job_finishes_on_the_other_worker_once(tmp_path, procs):
    root = tmp_path / "captures"
    make_captures(root)
    # The default lease: on one machine a dead worker's job is taken over at once, and a live worker that a busy
    # machine holds up for a few seconds keeps its job.
    argv = spadscan_argv("worker", "--root", root, "--processes", 1, "--steps", 2, "--device", "cpu",
                         "--poll-s", 0.2)
    workers = {p.pid: p for p in (procs.start(argv, "worker-a"), procs.start(argv, "worker-b"))}

    # The first job process to appear: its worker is the one to kill, mid-job, once the job watches its parent.
    job_pid, _ = next(iter(wait_for(lambda: job_processes(root), "a job process", 120).items()))
    wait_for(lambda: threads(job_pid) >= 2, "the job process under way", 60)
    victim = workers.pop(parent_pid(job_pid))
    (survivor,) = workers.values()
    victim.kill()
    victim.wait(timeout=30)
    wait_for(lambda: job_pid not in job_processes(root), "the orphaned job process to end", 30)

    queue = Queue.for_root(root)
    wait_for(lambda: queue.counts()["done"] == len(SCANS), "every job done", 400, poll_s=0.2)
    assert procs.stop(survivor) == 0, procs.log(survivor)
    assert not job_processes(root), "a job process outlived the stopped worker"

    r = spadscan("worker", "--root", root, "--status", "--json")
    assert r.returncode == 0, r.stderr
    rows = {row["id"]: row for row in json.loads(r.stdout)}
    assert sorted(rows) == [f"{s}-fast" for s in SCANS]
    assert {row["state"] for row in rows.values()} == {"done"}
    lost = []
    for scan in SCANS:
        job = f"{scan}-fast"
        outcomes = [rec["outcome"] for rec in queue.records(job)]
        assert outcomes.count("done") == 1, f"{job} reconstructed {outcomes.count('done')} times: {outcomes}"
        if "lost" in outcomes:
            lost.append(job)
            assert outcomes == ["lost", "done"], outcomes
            assert rows[job]["attempts"] == 2
        done = [rec for rec in queue.records(job) if rec["outcome"] == "done"][0]
        assert done["pid"] == survivor.pid or "lost" not in outcomes, "the retried job ran on the surviving worker"
        result = root / scan / "recon" / job
        assert Path(rows[job]["result"]) == result
        assert (result / "mesh.ply").is_file() and (result / "job.log").is_file()
        assert json.loads((result / "report.json").read_text())["steps"] == 2
        assert [p.name for p in (root / scan / "recon").iterdir() if not p.name.startswith(".")] == [job]
    assert len(lost) == 1, f"exactly the killed worker's job was taken over: {lost}"
    (taken,) = lost
    held = queue.records(taken)[0]
    assert held["pid"] == victim.pid, "the killed worker held it"
    said = f"{taken}: worker {held['host']} pid {victim.pid} died mid-job; queued again"
    assert said in procs.log(survivor), procs.log(survivor)


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(p) for p in (task / "children").read_text().split()]
        except OSError:
            continue
    return out


@pytest.mark.slow
def test_a_job_whose_worker_died_before_it_started_exits(tmp_path, procs):
    root = tmp_path / "captures"
    make_captures(root)
    # A long job: it cannot end by finishing its work while the test waits for it to notice its worker is gone.
    argv = spadscan_argv("worker", "--root", root, "--processes", 1, "--steps", 100000, "--budget-s", 600,
                         "--device", "cpu", "--poll-s", 0.2)
    worker = procs.start(argv, "worker")
    job = wait_for(lambda: children(worker.pid), "the worker to start a job process", 120, poll_s=0.001)[0]
    os.kill(job, signal.SIGSTOP)  # hold the job before it is under way
    try:
        if threads(job) > 1:
            pytest.skip("the job process armed its parent watch before it could be held")
        worker.kill()  # the worker dies while its job is starting
        worker.wait(timeout=30)
        os.kill(job, signal.SIGCONT)
        wait_for(lambda: not alive(job), "the orphaned job process to exit", 60, poll_s=0.1)
    finally:
        if alive(job):
            os.kill(job, signal.SIGKILL)


@pytest.mark.slow
def test_a_killed_workers_partial_result_is_cleaned_up(tmp_path, procs):
    root = tmp_path / "captures"
    make_captures(root)
    shutil.rmtree(root / SCANS[1])
    argv = spadscan_argv("worker", "--root", root, "--processes", 1, "--steps", 2, "--device", "cpu", "--poll-s", 0.2)
    first = procs.start(argv, "worker")
    job_pid = next(iter(wait_for(lambda: job_processes(root), "a job process", 120)))
    wait_for(lambda: threads(job_pid) >= 2, "the job process under way", 60)
    first.kill()
    first.wait(timeout=30)
    wait_for(lambda: job_pid not in job_processes(root), "the orphaned job process to end", 30)
    r = spadscan("worker", "--root", root, "--once", "--steps", 2, "--device", "cpu", timeout=300)
    assert r.returncode == 0, r.stderr
    recon = root / SCANS[0] / "recon"
    assert (recon / f"{SCANS[0]}-fast" / "mesh.ply").is_file()
    assert sorted(p.name for p in recon.iterdir()) == [f"{SCANS[0]}-fast"], "a partial result was left behind"
