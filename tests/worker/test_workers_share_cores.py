"""Workers on one machine share its CPU cores: a job's threads count the job processes of the other workers present
on that machine (their presence files), not only its own worker's, unless the user fixed the threads. Workers on
other machines that share the queue do not count."""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import pytest

from spadscan.cli import main as cli_main
from spadscan.worker.holder import Holder
from spadscan.worker.pool import Worker
from spadscan.worker.presence import Presence, machine_siblings, write_presence
from spadscan.worker.threads import ADAPT_ENV, ENV
from spadscan.worker.worker_config import WorkerConfig, machine_job_processes

from test_reclaim_note import dead_holder
from test_watcher import make_scan

HERE = Path(__file__).resolve().parent


def cores(monkeypatch, n: int) -> None:
    """The machine has `n` cores, as the worker's thread choice and its lines count them."""
    import spadscan.worker.threads as threads
    import spadscan.worker.worker_config as worker_config

    monkeypatch.setattr(threads, "machine_cores", lambda: n)
    monkeypatch.setattr(worker_config, "machine_cores", lambda: n)


def sibling(queue: Path, holder: Holder | None = None, processes: int = 1, token: str = "0badcafe") -> Holder:
    """Write the presence file another worker writes (`token`: rewrite the file of that one): by default a live
    process of this machine (the test runner's parent) with `processes` job processes. Renewed, as far as readers can
    tell, for an hour: the test may run on a busy machine."""
    holder = holder or Holder.of_pid(os.getppid())
    Path(queue).mkdir(parents=True, exist_ok=True)
    write_presence(queue, Presence(holder.to_dict(), "/captures", 1000.0, processes, renew_s=3600.0, token=token))
    return holder


@pytest.fixture
def no_user_threads(monkeypatch):
    for name in (ENV, ADAPT_ENV):
        monkeypatch.delenv(name, raising=False)


# ---- who counts ------------------------------------------------------------------------------------------------

def test_a_worker_on_this_machine_counts_idle_or_not(tmp_path):
    me = Holder.current().to_dict()
    other = sibling(tmp_path, processes=2)
    [row] = machine_siblings(tmp_path, me)
    assert (row["pid"], row["processes"]) == (other.pid, 2)
    assert machine_job_processes([row]) == 2, "an idle worker may claim a job at its next look"


def test_this_process_and_workers_gone_or_elsewhere_do_not_count(tmp_path):
    me = Holder.current()
    write_presence(tmp_path, Presence(me.to_dict(), "/captures", 1000.0, 4))  # this worker's own file
    sibling(tmp_path, dead_holder(), token="1")  # killed: its file stayed behind
    sibling(tmp_path, replace(me, host="elsewhere", boot_id="another-boot", pid=7), token="2")  # sharing the folder
    sibling(tmp_path, replace(me, boot_id="a-cloned-machine's", pid=8), token="3")  # one host name, another machine
    assert machine_siblings(tmp_path, me.to_dict()) == []
    container = sibling(tmp_path, replace(Holder.of_pid(os.getppid()), host="container", pid_ns="pid:[1]"),
                        token="4")
    [row] = machine_siblings(tmp_path, me.to_dict())  # another host name on this machine's kernel: its cores
    assert (row["host"], row["pid"]) == ("container", container.pid)


def test_a_siblings_job_processes_are_its_processes_at_least_its_running_jobs():
    assert machine_job_processes([{"processes": 2, "running": []}, {"processes": 1, "running": ["a"]}]) == 3
    assert machine_job_processes([{"processes": 0, "running": ["a", "b"]}]) == 2, "a damaged file: its jobs count"
    assert machine_job_processes([{"processes": -5, "running": []}]) == 1


# ---- the threads a job gets ------------------------------------------------------------------------------------

def test_the_cores_are_shared_out_among_every_workers_job_processes(monkeypatch):
    cores(monkeypatch, 2)
    config = WorkerConfig(root=Path("."), processes=1)
    assert config.job_env({})[ENV] == "2", "alone: both cores"
    assert config.job_env({}, others=1)[ENV] == "1"
    assert config.job_env({}, others=1)[ADAPT_ENV] == "1", "a share of the cores, which the job may go under"
    assert config.job_env({}, others=5)[ENV] == "1", "never fewer than one thread"
    assert config.threads_note({}, others=1) == ("1 CPU threads per job (OMP_NUM_THREADS=1: 2 cores shared out "
                                                 "among 2 job process(es))")


@pytest.mark.parametrize("threads, environ, why", [(2, {}, "set by --threads"),
                                                   (None, {ENV: "2"}, "the worker's own environment")])
def test_threads_the_user_fixed_are_kept_beside_other_workers(monkeypatch, threads, environ, why):
    cores(monkeypatch, 2)
    config = WorkerConfig(root=Path("."), processes=1, threads=threads)
    assert config.job_threads(environ, others=1) == 2 and ADAPT_ENV not in config.job_env(environ, others=1)
    rows = [{"host": "lab", "pid": 4242, "processes": 1, "running": []}]
    line = config.siblings_line(rows, environ, host="lab")
    # The threads that run in all, not only the job processes: the one worker it advises runs no more than cores.
    assert line == (f"another worker runs on this host (pid 4242, 1 job process(es)): 2 CPU threads per job "
                    f"(OMP_NUM_THREADS=2: {why}), kept; 2 job process(es) x 2 CPU thread(s) = 4 threads on 2 cores; "
                    f"one worker with --processes 2 does the same with less: one process watching the root and the "
                    f"queue, not 2"), line
    assert config.siblings_line(rows, environ, host="lab", threads_said=True).startswith(
        "another worker runs on this host (pid 4242, 1 job process(es)): the threads per job above kept; 2 job "
        "process(es) x 2 CPU thread(s) = 4 threads on 2 cores; one worker")
    [warning] = config.threads_warnings(environ, others=1)
    assert warning.startswith("2 job process(es) on this host (1 of this worker's, 1 of other workers') x 2 CPU "
                              "thread(s) = 4 threads on 2 cores"), warning


def test_more_job_processes_than_cores_on_the_machine_is_a_warning(monkeypatch):
    cores(monkeypatch, 2)
    config = WorkerConfig(root=Path("."), processes=2)
    assert config.threads_warnings({}, others=0) == []
    [warning] = config.threads_warnings({}, others=1)
    assert warning == ("3 job process(es) on this host (2 of this worker's, 1 of other workers') x 1 CPU thread(s) "
                       "= 3 threads on 2 cores: the jobs take turns on the cores, each run slower; stop a worker, or "
                       "run one worker with --processes 2")
    # The line that names the other worker advises the same one worker: no more job processes than cores.
    line = config.siblings_line([{"host": "lab", "pid": 4242, "processes": 1, "running": []}], {}, host="lab")
    assert line.endswith("; one worker with --processes 2 does the same with less: one process watching the root "
                         "and the queue, not 2"), line


def test_the_siblings_line_names_them_and_the_single_worker_that_does_the_same(monkeypatch):
    cores(monkeypatch, 2)
    config = WorkerConfig(root=Path("."), processes=1)
    rows = [{"host": "lab", "pid": 4242, "processes": 1, "running": []},
            {"host": "box", "pid": 9, "processes": 2, "running": ["s-fast"]}]
    assert config.siblings_line(rows[:1], {}, host="lab") == (
        "another worker runs on this host (pid 4242, 1 job process(es)): 1 CPU threads per job (OMP_NUM_THREADS=1: "
        "2 cores shared out among 2 job process(es)); one worker with --processes 2 does the same with less: one "
        "process watching the root and the queue, not 2")
    assert config.siblings_line(rows, {}, host="lab").startswith(
        "2 other workers run on this host (pid 4242, box pid 9, 3 job process(es)): 1 CPU threads per job")
    assert config.siblings_line([], {}, host="lab") == (
        "no other worker runs on this host now: 2 CPU threads per job (OMP_NUM_THREADS=2: 2 cores shared out among "
        "1 job process(es))")


# ---- the worker ------------------------------------------------------------------------------------------------

def test_a_worker_that_starts_beside_another_says_so_once(tmp_path, monkeypatch, arun, no_user_threads):
    cores(monkeypatch, 2)
    root = tmp_path / "captures"
    root.mkdir()
    other = sibling(root / ".queue")
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05), log=lines.append)
    arun(worker.run(), timeout_s=60)
    assert lines[0].endswith("1 CPU threads per job (OMP_NUM_THREADS=1: 2 cores shared out among 2 job process(es))")
    # The threads per job said once: the line that names the other worker follows the one that says them.
    assert lines[1] == (f"another worker runs on this host (pid {other.pid}, 1 job process(es)), counted in the "
                        "threads per job above; one worker with --processes 2 does the same with less: one process "
                        "watching the root and the queue, not 2"), lines
    assert sum("other worker" in line for line in lines) == 1, lines
    assert worker.job_env[ENV] == "1"


def test_a_worker_looks_again_when_a_job_starts_and_says_only_a_change(tmp_path, monkeypatch, arun,
                                                                       no_user_threads):
    cores(monkeypatch, 2)
    root = tmp_path / "captures"
    root.mkdir()
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, poll_s=0.05), log=lines.append)
    worker._share_cores(machine_siblings(worker.queue.path, worker.presence.holder))  # as at start-up: alone
    assert worker.job_env[ENV] == "2" and lines == []
    other = sibling(worker.queue.path)
    arun(worker._share_cores_now())
    assert worker.job_env[ENV] == "1"
    assert lines == [f"another worker runs on this host (pid {other.pid}, 1 job process(es)): 1 CPU threads per "
                     "job (OMP_NUM_THREADS=1: 2 cores shared out among 2 job process(es)); one worker with "
                     "--processes 2 does the same with less: one process watching the root and the queue, not 2"]
    arun(worker._share_cores_now())
    assert len(lines) == 1, "the same workers: nothing more to say"
    sibling(worker.queue.path, Holder.of_pid(os.getppid()), processes=2)  # it now runs two at once
    arun(worker._share_cores_now())
    assert len(lines) == 3 and "(pid" in lines[1] and lines[2].startswith("warning: 3 job process(es) on this host")
    for path in (worker.queue.path / "workers").glob("*.json"):
        path.unlink()  # it stopped
    arun(worker._share_cores_now())
    assert worker.job_env[ENV] == "2" and lines[3].startswith("no other worker runs on this host now: 2 CPU threads")


def env_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
              started=None):
    """A stand-in reconstruction that reports the threads its process was given."""
    report = {"omp_num_threads": os.environ.get(ENV)}
    (Path(out) / "report.json").write_text(json.dumps(report))
    return report


def test_each_jobs_threads_and_log_count_the_workers_beside_it(tmp_path, monkeypatch, arun, no_user_threads):
    """Real job processes: a worker that started alone, another starting beside it before its job does, gives the
    job its share of the cores, says so once, and the job's log (the result's job.log) names that worker, where a
    busy warning in its report may come from."""
    cores(monkeypatch, 2)
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "s")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")]))
    lines: list[str] = []
    others: list[Holder] = []

    def log(line: str) -> None:
        lines.append(line)
        if line.startswith("watching"):  # started alone; the other worker starts before the job does
            others.append(sibling(root / ".queue"))

    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05, recon="test_workers_share_cores:env_recon"),
                    log=log)
    assert arun(worker.run(), timeout_s=120) == {"s-fast": "done"}, lines
    assert lines[0].endswith("2 CPU threads per job (OMP_NUM_THREADS=2: 2 cores shared out among 1 job process(es))")
    said = [i for i, line in enumerate(lines) if line.startswith("another worker runs on this host")]
    started = next(i for i, line in enumerate(lines) if line.startswith("s-fast started"))
    assert len(said) == 1 and said[0] < started, lines
    assert f"(pid {others[0].pid}, 1 job process(es)): 1 CPU threads per job" in lines[said[0]]
    result = root / "s" / "recon" / "s-fast"
    assert json.loads((result / "report.json").read_text())["omp_num_threads"] == "1"
    first = (result / "job.log").read_text().splitlines()[0]
    assert first == f"spadscan worker: {lines[said[0]]}", first


def test_help_says_that_workers_on_one_machine_share_its_cores(capsys):
    with pytest.raises(SystemExit):
        cli_main(["worker", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "the job processes of the other workers on this machine" in text
    assert "workers on other machines sharing the queue do not count" in text
