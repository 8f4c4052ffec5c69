"""CPU threads per job: every job process is told how many threads to use (OMP_NUM_THREADS), so that jobs running at
once share the cores instead of stalling each other (worker/threads.py has the measurements)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from spadscan.cli import main as cli_main
from spadscan.worker.pool import Worker
from spadscan.worker.threads import (ADAPT_ENV, ENV, SHORT_SPIN, SPIN_ENV, WAIT_ENV, ThreadGovernor, machine_cores,
                                     oversubscribed, threads_fixed)
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan

HERE = Path(__file__).resolve().parent


def threads_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto", seed=0,
                started=None):
    """A stand-in reconstruction that reports the threads its process was given and the ones torch uses."""
    import torch  # after the process started: torch reads OMP_NUM_THREADS when it is imported

    report = {"omp_num_threads": os.environ.get(ENV), "torch_threads": torch.get_num_threads()}
    (Path(out) / "report.json").write_text(json.dumps(report))
    return report


def run_jobs(tmp_path, monkeypatch, arun, **config) -> tuple[list[dict], list[str]]:
    """Run a worker with `config` over two scans until both are done; the jobs' reports and the worker's log."""
    root = tmp_path / "captures"
    root.mkdir()
    for name in ("a", "b"):
        make_scan(root, name)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")]))
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.1, recon="test_worker_threads:threads_recon",
                                 **config), log=lines.append)
    assert arun(worker.run(), timeout_s=120) == {"a-fast": "done", "b-fast": "done"}, lines
    reports = [json.loads((root / n / "recon" / f"{n}-fast" / "report.json").read_text()) for n in ("a", "b")]
    return reports, lines


def threads_seen(reports: list[dict]) -> list[str]:
    """OMP_NUM_THREADS of each job, after checking torch kept to it (torch caps it at the cores it sees)."""
    for r in reports:
        n = int(r["omp_num_threads"])
        assert r["torch_threads"] == 1 if n == 1 else 1 <= r["torch_threads"] <= n, r
    return [r["omp_num_threads"] for r in reports]


def test_jobs_share_the_cores_by_default(tmp_path, monkeypatch, arun):
    monkeypatch.delenv(ENV, raising=False)
    reports, lines = run_jobs(tmp_path, monkeypatch, arun, processes=2)
    share = max(1, machine_cores() // 2)
    assert threads_seen(reports) == [str(share)] * 2
    assert any(f"{share} CPU threads per job" in line and "shared out among 2" in line for line in lines), lines


def test_threads_given_are_what_each_job_gets(tmp_path, monkeypatch, arun):
    monkeypatch.setenv(ENV, "5")  # --threads wins over the worker's own environment
    reports, lines = run_jobs(tmp_path, monkeypatch, arun, processes=2, threads=3)
    assert threads_seen(reports) == ["3"] * 2
    assert any("3 CPU threads per job" in line and "--threads" in line for line in lines), lines


def test_the_workers_own_omp_num_threads_is_kept(tmp_path, monkeypatch, arun):
    monkeypatch.setenv(ENV, "5")
    reports, lines = run_jobs(tmp_path, monkeypatch, arun, processes=2)
    assert threads_seen(reports) == ["5"] * 2
    assert any("5 CPU threads per job" in line and "own environment" in line for line in lines), lines


def test_child_env_wins_over_threads():
    config = WorkerConfig(root=Path("."), processes=2, threads=3, child_env={ENV: "4", "OTHER": "x"})
    assert config.job_env({}) == {ENV: "4", "OTHER": "x", WAIT_ENV: "PASSIVE"}, "fixed threads wait passively"
    assert WorkerConfig(root=Path("."), processes=2).job_env({ENV: "7"}) == {WAIT_ENV: "PASSIVE"}, \
        "the user's choice is inherited"


def test_jobs_adapt_only_the_threads_the_worker_chose_and_spin_briefly_only_then(monkeypatch):
    two_cores(monkeypatch)
    config = WorkerConfig(root=Path("."), processes=1)
    assert config.job_env({}) == {ENV: "2", ADAPT_ENV: "1", SPIN_ENV: SHORT_SPIN}
    assert WorkerConfig(root=Path("."), processes=1, threads=2).job_env({})[WAIT_ENV] == "PASSIVE"
    assert ADAPT_ENV not in WorkerConfig(root=Path("."), processes=1, threads=2).job_env({}), "--threads is kept"
    assert config.job_env({WAIT_ENV: "ACTIVE"}) == {ENV: "2", ADAPT_ENV: "1"}, "the user's wait policy is kept"
    assert config.job_env({SPIN_ENV: "1000"}) == {ENV: "2", ADAPT_ENV: "1"}, "the user's spin count is kept"
    assert threads_fixed(3, {}) and threads_fixed(None, {ENV: "2"}) and not threads_fixed(None, {})
    assert not threads_fixed(None, {ENV: "2", ADAPT_ENV: "1"})


@pytest.mark.parametrize("argv, env, want", [
    ([], {}, (SHORT_SPIN, "")),  # the governor chooses: a short spin
    (["--threads", "2"], {}, ("", "PASSIVE")),  # fixed: no governor to leave a stalled pair
    ([], {ENV: "2"}, ("", "PASSIVE")),  # the user's OMP_NUM_THREADS is fixed too
    ([], {ENV: "2", ADAPT_ENV: "1"}, (SHORT_SPIN, "")),  # a worker's share of the cores adapts
    ([], {WAIT_ENV: "ACTIVE"}, ("", "ACTIVE")),  # the user's wait policy is kept
    (["--threads", "2"], {SPIN_ENV: "500"}, ("500", "")),  # and the user's spin count
])
def test_reconstruct_sets_how_threads_wait_before_torch_starts(tmp_path, monkeypatch, capsys, argv, env, want):
    for name in (ENV, ADAPT_ENV, WAIT_ENV, SPIN_ENV):
        monkeypatch.setenv(name, env.get(name, ""))  # restored after the test: the command writes os.environ
    missing = tmp_path / "no-capture"
    assert cli_main(["reconstruct", str(missing), "--out", str(tmp_path / "out"), *argv]) != 0
    assert (os.environ[SPIN_ENV], os.environ[WAIT_ENV]) == want


@pytest.mark.parametrize("bad", ["0", "-2", "2000"])
def test_bad_threads_are_a_one_line_error(tmp_path, capsys, bad):
    assert cli_main(["worker", "--root", str(tmp_path), "--once", "--threads", bad]) == 1
    err = capsys.readouterr().err
    assert f"threads {bad} must be an integer in [1, 1024]" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / ".queue").exists(), "nothing queued with a bad option"


def test_help_says_what_threads_does(capsys):
    with pytest.raises(SystemExit):
        cli_main(["worker", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--threads N" in text and "OMP_NUM_THREADS" in text and "shared out among --processes" in text


def two_cores(monkeypatch):
    import spadscan.worker.threads as threads

    monkeypatch.setattr(threads, "machine_cores", lambda: 2)


@pytest.mark.parametrize("processes, threads, environ, total", [
    (2, 4, {}, 8),  # --processes 2 --threads 4
    (2, None, {ENV: "8"}, 16),  # an inherited OMP_NUM_THREADS
    (4, 1, {}, 4),  # more single-threaded jobs than cores
])
def test_more_threads_than_cores_is_a_warning(monkeypatch, processes, threads, environ, total):
    two_cores(monkeypatch)
    config = WorkerConfig(root=Path("."), processes=processes, threads=threads)
    (warning,) = config.threads_warnings(environ)
    assert warning.startswith(f"{processes} job process(es) x {total // processes} CPU thread(s) = {total} threads "
                              "on 2 cores")
    assert ("20-40x slower; use --threads 1" in warning) == (total // processes > 1)


@pytest.mark.parametrize("processes, threads, others, warning", [
    (3, 1, 0, "3 job process(es) x 1 CPU thread(s) = 3 threads on 2 cores: the jobs take turns on the cores; "
              "--processes 2 runs as many at once as there are cores"),
    (2, 2, 0, "2 job process(es) x 2 CPU thread(s) = 4 threads on 2 cores: OpenMP threads that lose their core stall "
              "each other, each step 20-40x slower; use --threads 1"),
    (2, 1, 1, "3 job process(es) on this host (2 of this worker's, 1 of other workers') x 1 CPU thread(s) = 3 threads "
              "on 2 cores: the jobs take turns on the cores, each run slower; stop a worker, or run one worker with "
              "--processes 2"),
    (1, 2, 1, "2 job process(es) on this host (1 of this worker's, 1 of other workers') x 2 CPU thread(s) = 4 threads "
              "on 2 cores: OpenMP threads that lose their core stall each other, each step 20-40x slower; use "
              "--threads 1 in each worker"),
    (2, 1, 0, None),  # as many threads as cores: they fit
    (1, 1, 1, None),
])
def test_oversubscribed_words_a_worker_alone_and_beside_others(processes, threads, others, warning):
    # One rule, two wordings: other workers' job processes are counted apart and the advice speaks to every worker.
    assert oversubscribed(processes, threads, 2, others=others) == warning


def test_threads_that_fit_the_cores_are_no_warning(monkeypatch):
    two_cores(monkeypatch)
    assert WorkerConfig(root=Path("."), processes=2).threads_warnings({}) == []
    assert WorkerConfig(root=Path("."), processes=1, threads=2).threads_warnings({ENV: "8"}) == []


@pytest.mark.parametrize("bad", ["abc", "0", "-1", "2.5", "+2", "1_0", "\u0663", "2048", "1" * 5000])
def test_an_unusable_omp_num_threads_is_ignored_with_a_warning(monkeypatch, bad):
    two_cores(monkeypatch)
    config = WorkerConfig(root=Path("."), processes=2)
    assert config.job_env({ENV: bad}) == {ENV: "1", ADAPT_ENV: "1", SPIN_ENV: SHORT_SPIN}, \
        "the jobs get the cores shared out instead"
    assert config.threads_warnings({ENV: bad}) == [
        f"{ENV}={bad!r} in the worker's environment is not a whole number in [1, 1024]: ignored"]
    assert config.threads_note({ENV: bad}).startswith("1 CPU threads per job (OMP_NUM_THREADS=1: 2 cores shared")
    assert WorkerConfig(root=Path("."), processes=2, threads=1).threads_warnings({ENV: bad}) == [], \
        "--threads given: the environment's value does not matter"


def test_the_worker_logs_its_thread_warnings(tmp_path, monkeypatch, arun):
    monkeypatch.setenv(ENV, "abc")
    reports, lines = run_jobs(tmp_path, monkeypatch, arun, processes=2)
    assert threads_seen(reports) == [str(max(1, machine_cores() // 2))] * 2
    assert f"warning: {ENV}='abc' in the worker's environment is not a whole number in [1, 1024]: ignored" in lines


# ---- choosing threads as the run goes ----------------------------------------------------------------------------

class Machine:
    """Step times of a 2-core machine: `seconds[n]` a step with n threads; `set_threads` is what torch is told."""

    def __init__(self, seconds: dict[int, float]):
        self.seconds, self.told = dict(seconds), []

    def set_threads(self, n: int) -> None:
        self.told.append(n)

    def run(self, governor: ThreadGovernor, steps: int) -> list[int]:
        used = []
        for _ in range(steps):
            used.append(governor.threads)
            governor.step_done(self.seconds[governor.threads])
        return used


def test_an_idle_machine_keeps_both_threads_when_they_are_faster():
    machine = Machine({2: 0.050, 1: 0.055})
    governor = ThreadGovernor(2, machine.set_threads)
    used = machine.run(governor, 2000)
    assert used.count(2) > 0.97 * len(used) and governor.switches == 1  # from the one thread it starts with
    assert governor.probes <= 8, "a choice confirmed again and again is checked less and less often"


def test_a_machine_busy_from_the_start_never_waits_on_a_stalled_second_thread():
    """Two threads beside a busy process stall each step (1.1 s against 0.07 s with one): a run that starts with them
    spends its first steps, up to half a short budget, stalled. It starts with one, and its probe of two is cut at
    the first stalled step."""
    machine = Machine({2: 1.1, 1: 0.07})
    governor = ThreadGovernor(2, machine.set_threads)
    assert machine.told == [1] and governor.threads == 1
    used = machine.run(governor, 300)
    assert used[:13] == [1] * 13 and used.count(2) == 1
    assert sum(machine.seconds[n] for n in used) < 300 * 0.07 + 1.1


def test_a_stalled_second_thread_falls_back_to_one_and_returns_when_the_competitor_leaves():
    machine = Machine({2: 0.050, 1: 0.055})
    governor = ThreadGovernor(2, machine.set_threads)
    machine.run(governor, 300)
    machine.seconds[2] = 2.6  # a competitor takes a core: two threads stall each other at every barrier
    used = machine.run(governor, 400)
    assert used[:3].count(2) <= 2 and used[3:].count(2) <= 1, "falls back at once; a later check costs one step"
    assert governor.threads == 1 and sum(machine.seconds[n] for n in used) < 400 * 0.055 + 3 * 2.6
    machine.seconds[2] = 0.050  # the competitor is gone
    used = machine.run(governor, 3000)
    assert used[-1000:].count(2) > 950, "two threads again once they are faster"


def test_one_thread_is_kept_when_two_are_no_faster():
    machine = Machine({2: 0.054, 1: 0.055})  # under the margin: one thread never stalls
    governor = ThreadGovernor(2, machine.set_threads)
    used = machine.run(governor, 1000)
    assert used[-500:].count(1) > 480 and machine.told[-1] == 1
    assert governor.summary()["steps_by_threads"]["1"] > 900


def test_a_governor_needs_two_threads_to_choose_from():
    from spadscan.protocol.errors import ConfigError

    with pytest.raises(ConfigError):
        ThreadGovernor(1, lambda n: None)
