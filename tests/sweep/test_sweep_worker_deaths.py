"""A point whose worker process died says what is known of how it ended: the signal's name where a signal ended it
(SIGKILL: out of memory or killed by hand; SIGSEGV: a crash; SIGTERM: stopped), else the exit code, and which
worker's log says why; or, where the nanny itself stopped the worker for using more than its memory limit, how much
it used of which limit (the silenced log does not say). Only a worker's nanny learns that: the embedded cluster's
nannies report it; a scheduler's workers do not, and there the point says only that its worker died."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
from types import SimpleNamespace

import pytest
from distributed import KilledWorker

from spadscan.sweep.plan import make_plan
from spadscan.sweep.runner import WorkerExits, killed_worker_reason, process_ending, worker_memory_limit
from spadscan.sweep.spec import load_spec

KILLED = "was killed (SIGKILL: out of memory, or killed by hand?)"
NANNY = "tcp://127.0.0.1:40000"
WORKER = SimpleNamespace(address="tcp://127.0.0.1:40001", name="w1", pid=4242, nanny=NANNY)


@pytest.mark.parametrize(("exitcode", "said"), [
    (-9, KILLED), (-11, "crashed (SIGSEGV)"), (-6, "crashed (SIGABRT)"), (-15, "was stopped (SIGTERM)"),
    (-10, "was ended by SIGUSR1"), (1, "exited with code 1"), (None, "died"),
])
def test_how_a_process_ended_is_said_from_its_exit_status(exitcode, said):
    assert process_ending(exitcode) == said


def _exits(**codes) -> WorkerExits:
    exits = WorkerExits()
    for address, code in codes.items():
        exits.note((0.0, {"worker": address, "exitcode": code}))
    return exits


def test_the_embedded_clusters_worker_says_its_signal_and_where_it_writes():
    exits = _exits(**{WORKER.address: -9})
    assert killed_worker_reason(KilledWorker("k", WORKER, 0), exits) == (
        f"the worker running it {KILLED}; its log says why (worker w1, pid 4242, writing to this command's stderr)")
    assert killed_worker_reason(KilledWorker("k", WORKER, 2), exits) == (
        f"the worker running it died each time it was tried (3 workers; the last {KILLED}); their logs say why "
        f"(the last: worker w1, pid 4242, writing to this command's stderr)")


MIB = 2**20
MEMORY = {"rss": 480 * MIB, "limit": 300 * MIB, "machine": 600 * MIB, "terminate": 0.95}


def test_a_worker_its_nanny_stopped_for_its_memory_says_so_and_no_log_is_pointed_to():
    exits = WorkerExits()
    exits.note((0.0, {"worker": WORKER.address, "nanny": NANNY, "exitcode": -15, "memory": MEMORY}))
    stopped = ("was stopped by Dask for using too much memory: 480.00 MiB, more than 95% of its 300.00 MiB limit, "
               "its share of this machine's 600.00 MiB (fewer --workers give each more)")
    assert killed_worker_reason(KilledWorker("k", WORKER, 0), exits) == (
        f"the worker running it (worker w1, pid 4242) {stopped}")
    assert killed_worker_reason(KilledWorker("k", WORKER, 1), exits) == (
        f"the worker running it died each time it was tried (2 workers); the last (worker w1, pid 4242) {stopped}")


def test_a_worker_that_had_the_whole_machine_is_not_told_to_share_it():
    exits = WorkerExits()
    whole = {**MEMORY, "limit": 600 * MIB}
    exits.note((0.0, {"worker": WORKER.address, "nanny": NANNY, "exitcode": -9, "memory": whole}))
    assert killed_worker_reason(KilledWorker("k", WORKER, 0), exits) == (
        "the worker running it (worker w1, pid 4242) was stopped by Dask for using too much memory: 480.00 MiB, "
        "more than 95% of its 600.00 MiB limit")


@pytest.mark.parametrize("memory", ["480 MB", {**MEMORY, "rss": None}, {**MEMORY, "limit": True},
                                    {**MEMORY, "terminate": 95}, {k: v for k, v in MEMORY.items() if k != "machine"}])
def test_a_malformed_memory_report_leaves_the_signal(memory):
    exits = WorkerExits()
    exits.note((0.0, {"worker": WORKER.address, "nanny": NANNY, "exitcode": -15, "memory": memory}))
    assert killed_worker_reason(KilledWorker("k", WORKER, 0), exits).startswith(
        "the worker running it was stopped (SIGTERM); its log says why")


def test_the_embedded_clusters_workers_share_the_machines_memory(monkeypatch):
    from distributed import system

    monkeypatch.setattr(system, "MEMORY_LIMIT", 16 * 2**30)
    assert [worker_memory_limit(n) for n in (1, 4)] == [16 * 2**30, 4 * 2**30]


def test_a_schedulers_worker_is_said_to_have_died_without_a_guessed_cause():
    assert killed_worker_reason(KilledWorker("k", WORKER, 0), None) == (
        "the worker running it died; its log says why (worker w1, pid 4242, at tcp://127.0.0.1:40001)")


def test_a_report_that_never_comes_leaves_it_at_died(monkeypatch):
    from spadscan.sweep import runner

    monkeypatch.setattr(runner, "EXIT_NOTE_S", 0.01)
    reason = killed_worker_reason(KilledWorker("k", WORKER, 0), _exits(**{"tcp://127.0.0.1:1": -11}))
    assert reason.startswith("the worker running it died; its log says why"), reason


def test_a_report_that_comes_after_dasks_verdict_is_waited_for():
    exits = WorkerExits()
    waiting = threading.Event()
    found = []

    def ask():
        waiting.set()
        found.append(exits.wait_for(WORKER.address, NANNY, 60))

    asker = threading.Thread(target=ask)
    asker.start()
    waiting.wait(60)
    exits.note((0.0, {"worker": "tcp://elsewhere:1", "nanny": "tcp://elsewhere:0", "exitcode": -15}))  # not its
    exits.note((0.0, {"worker": WORKER.address, "exitcode": -11}))
    asker.join(60)
    assert found == [-11]


def test_a_malformed_report_is_left_out():
    exits = WorkerExits()
    for message in ("text", {"worker": WORKER.address}, {"worker": WORKER.address, "exitcode": True},
                    {"worker": 3, "exitcode": -9}):
        exits.note((0.0, message))
    assert exits.wait_for(WORKER.address, NANNY, 0) is None


def _returns_at_once(call) -> list:
    """What `call()` returns, asked on a thread that must end long before the hour `call` may wait."""
    found = []
    asker = threading.Thread(target=lambda: found.append(call()), daemon=True)
    asker.start()
    asker.join(60)
    assert not asker.is_alive(), "it waited"
    return found


def test_a_worker_that_died_before_its_nanny_knew_its_address_ends_one_wait_at_died():
    # It died as it started: its nanny reports the exit without an address. One wait for a worker of that nanny ends
    # at once, saying nothing of the ending (the report may be another worker's of that nanny).
    exits = WorkerExits()
    exits.note((0.0, {"worker": None, "nanny": NANNY, "exitcode": 1}))
    assert _returns_at_once(lambda: exits.wait_for(WORKER.address, NANNY, 3600)) == [None]
    exits.note((0.0, {"worker": WORKER.address, "nanny": NANNY, "exitcode": -9}))
    assert exits.wait_for(WORKER.address, NANNY, 0) == -9, "a named report is the worker's own"


def test_nannies_that_never_report_are_waited_for_once():
    exits = WorkerExits()
    assert exits.wait_for(WORKER.address, NANNY, 0.01) is None
    assert _returns_at_once(lambda: exits.wait_for("tcp://127.0.0.1:40002", NANNY, 3600)) == [None]
    # Once a report has come, the nannies do report: a report that comes after Dask's verdict is waited for again.
    exits.note((0.0, {"worker": WORKER.address, "nanny": NANNY, "exitcode": -9}))
    _report_after_the_verdict(exits)


def _report_after_the_verdict(exits: WorkerExits) -> None:
    later = "tcp://127.0.0.1:40003"
    waiting, found = threading.Event(), []

    def ask():
        waiting.set()
        found.append(exits.wait_for(later, NANNY, 60))

    asker = threading.Thread(target=ask)
    asker.start()
    waiting.wait(60)
    exits.note((0.0, {"worker": later, "nanny": NANNY, "exitcode": -11}))
    asker.join(60)
    assert found == [-11]


SIGNALLER = """
import sys
from pathlib import Path

import dask

from spadscan.sweep.plan import make_plan
from spadscan.sweep.runner import run_sweep
from spadscan.sweep.spec import load_spec


def ends_its_worker(task, out, device, keep):
    import os
    import resource
    import signal

    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))  # a SIGSEGV leaves no core file behind
    if sys.argv[3].startswith("SIG"):
        os.kill(os.getpid(), getattr(signal, sys.argv[3]))
    os._exit(int(sys.argv[3]))


if __name__ == "__main__":
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        summary = run_sweep(make_plan(load_spec(sys.argv[1])), Path(sys.argv[2]), workers=1, progress=False,
                            point=ends_its_worker)
    print(summary.ran, summary.done, len(summary.failed))
"""


@pytest.mark.slow
@pytest.mark.parametrize(("name", "said"), [
    ("SIGKILL", KILLED), ("SIGSEGV", "crashed (SIGSEGV)"), ("SIGTERM", "was stopped (SIGTERM)"),
    ("3", "exited with code 3"),
])
def test_a_point_says_which_signal_ended_its_worker(tmp_path, name, said):
    # One point a run: a worker that dies takes the blame for every point it held, run or waiting.
    spec = tmp_path / "one.toml"
    spec.write_text('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nviews = 4\n')
    script = tmp_path / "signaller.py"
    script.write_text(SIGNALLER)
    run = subprocess.run([sys.executable, str(script), str(spec), str(tmp_path / "out"), name], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.split() == ["1", "0", "1"]
    task = next(iter(make_plan(load_spec(spec)).points.values()))
    stored = json.loads((tmp_path / "out" / "points" / f"{task.id}.json").read_text())
    assert stored["status"] == "failed"
    assert re.fullmatch(rf"the worker running it {re.escape(said)}; its log says why \(worker \d+, pid \d+, writing "
                        r"to this command's stderr\)", stored["reason"]), stored["reason"]


MEMORY_HOG = """
import sys
from pathlib import Path

import dask
from distributed import system

from spadscan.sweep.plan import make_plan
from spadscan.sweep.runner import run_sweep
from spadscan.sweep.spec import load_spec


def uses_too_much_memory(task, out, device, keep):
    import time

    import numpy as np
    from distributed import get_worker

    limit = get_worker().memory_manager.memory_limit
    held = [np.ones(limit // 8 // 8) for _ in range(8)]  # its limit, on top of what the worker holds already
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:  # its nanny looks every 100 ms, and stops it
        time.sleep(0.05)
    raise RuntimeError(f"not stopped, holding {sum(a.nbytes for a in held)} bytes")


if __name__ == "__main__":
    system.MEMORY_LIMIT = int(sys.argv[3])  # the machine's memory, as Dask sees it: the worker gets all of it
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        summary = run_sweep(make_plan(load_spec(sys.argv[1])), Path(sys.argv[2]), workers=1, progress=False,
                            point=uses_too_much_memory)
    print(summary.ran, summary.done, len(summary.failed))
"""


@pytest.mark.slow
def test_a_point_whose_worker_dask_stopped_for_its_memory_says_so(tmp_path):
    spec = tmp_path / "one.toml"
    spec.write_text('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nviews = 4\n')
    script = tmp_path / "memory_hog.py"
    script.write_text(MEMORY_HOG)
    limit = 640 * 2**20  # above what a worker holds as it starts (about 300 MiB, torch loaded)
    run = subprocess.run([sys.executable, str(script), str(spec), str(tmp_path / "out"), str(limit)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.split() == ["1", "0", "1"]
    task = next(iter(make_plan(load_spec(spec)).points.values()))
    stored = json.loads((tmp_path / "out" / "points" / f"{task.id}.json").read_text())
    assert stored["status"] == "failed"
    # A single worker has the whole machine's memory, and is not told to share it.
    assert re.fullmatch(r"the worker running it \(worker \d+, pid \d+\) was stopped by Dask for using too much "
                        r"memory: [\d.]+ MiB, more than 95% of its 640.00 MiB limit", stored["reason"]), \
        stored["reason"]
