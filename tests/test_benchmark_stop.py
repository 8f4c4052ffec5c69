"""Nothing a benchmark starts outlives it: stopped by a time limit's SIGTERM it stops its competitors, runs, daemon
and workers itself (and prints what it measured so far); killed outright, they notice it is gone and stop.

Each benchmark runs in a process of its own, its slow part (a reconstruction, a live job, a scan) stood in for by a
wait, so that the test can signal it while its processes run; the ablation's run is a real one (a fit that would go on
for 10^6 steps), stopped as a user's Ctrl-C stops it. Every wait is for an event, with a generous timeout."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from benchmark_helpers import children, kill_all, load_benchmark, start_main, tiny_capture, wait_gone
from spadscan import parent_watch

STOPS = [pytest.param(signal.SIGTERM, id="SIGTERM"), pytest.param(signal.SIGKILL, id="SIGKILL")]


def read_until(proc: subprocess.Popen, prefix: str) -> str:
    """The first line of `proc`'s output that starts with `prefix` (AssertionError, with its errors, if it ends
    before one)."""
    for line in proc.stdout:
        if line.startswith(prefix):
            return line.strip()
    raise AssertionError(f"the benchmark ended before it said {prefix!r}: {proc.stderr.read()[-2000:]}")


CONTENTION = """
import time
def run_reconstruct(capture, out, budget_s):
    if not out.name.endswith("-2"):  # the idle run: measured
        return {"steps": 120, "seconds": 10.0, "torch_threads": 1}
    print("running", flush=True)  # beside the two competitors: stopped there
    time.sleep(3600)
bench.run_reconstruct = run_reconstruct
"""


def stop_and_wait(proc, how, spinners: set[int], what: str) -> tuple[str, str]:
    """Send the benchmark `how` once its two spinning processes run; (its stdout, its stderr) once it has ended and
    they are gone."""
    assert len(spinners) == 2
    proc.send_signal(how)
    out, err = proc.communicate(timeout=120)
    assert not wait_gone(spinners), f"{what} outlived the benchmark"
    return out, err


@pytest.mark.parametrize("how", STOPS)
def test_contention_leaves_no_competitor_and_no_temporary_folder(tmp_path, how):
    capture = tmp_path / "capture"
    capture.mkdir()
    (capture / "scan.json").write_text("{}")
    proc = start_main("contention", ["--capture", capture, "--budget-s", 30, "--busy", "0,2"], CONTENTION,
                      env={**os.environ, "TMPDIR": str(tmp_path)})
    spinners: set[int] = set()
    try:
        read_until(proc, "running")
        spinners = children(proc.pid)
        out, err = stop_and_wait(proc, how, spinners, "a competitor")
        if how == signal.SIGTERM:
            assert proc.returncode == 130 and "Traceback" not in err, err
            assert "interrupted: 1 of 2 runs measured" in err
            idle = [line.split() for line in out.splitlines() if line.split()[:1] == ["0"]]
            assert idle and idle[0][5] == "12.00"  # the idle run's 120 steps in 10 s, not lost
            assert not list(tmp_path.glob("contention-*"))  # the temporary folder is removed
    finally:
        kill_all(proc, spinners)


def test_contentions_reconstruct_stops_with_the_benchmark(tmp_path, monkeypatch):
    bench = load_benchmark("contention")
    seen = {}

    def fake_run(cmd, env=None, **kwargs):
        seen["env"] = env
        out = Path(cmd[cmd.index("--out") + 1])
        out.mkdir(parents=True)
        (out / "report.json").write_text('{"steps": 1, "seconds": 1.0}')
        return subprocess.CompletedProcess(cmd, 0, stderr="")

    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    monkeypatch.setattr(bench.subprocess, "run", fake_run)
    bench.run_reconstruct(tmp_path / "capture", tmp_path / "run", 5.0)
    # Named as its parent: a benchmark killed outright leaves no reconstruction running for nobody.
    assert seen["env"][parent_watch.ENV] == str(os.getpid())
    assert "OMP_NUM_THREADS" not in seen["env"]  # still the default's own thread count


LIVE_REFITS = """
import time
def follow(source, root, name, every_s):
    print("following", flush=True)
    time.sleep(3600)
bench.follow = follow
"""


@pytest.mark.parametrize("how", STOPS)
def test_live_refits_busy_processes_stop_with_it(tmp_path, how):
    # A scan of the scene and views asked for, in --out: not simulated again.
    load_benchmark("live_refits").simulate("sphere", 2, tmp_path / "out" / "source")
    proc = start_main("live_refits", ["--scene", "sphere", "--views", 2, "--busy", 2, "--out", tmp_path / "out"],
                      LIVE_REFITS)
    busy: set[int] = set()
    try:
        read_until(proc, "following")
        busy = children(proc.pid)
        out, err = stop_and_wait(proc, how, busy, "a busy process")
        if how == signal.SIGTERM:
            assert proc.returncode == 130 and "Traceback" not in err, err
            assert "interrupted: 0 of 2 rules measured" in err
    finally:
        kill_all(proc, busy)


LIVE = """
import time
def scan_and_follow(rig, *args, **kwargs):
    print("daemon", rig.daemon.pid, rig.sock_dir, flush=True)
    time.sleep(3600)
bench.scan_and_follow = scan_and_follow
"""


@pytest.mark.parametrize("how", STOPS)
def test_lives_daemon_stops_with_it(tmp_path, how):
    proc = start_main("live", ["--scenes", "sphere", "--overhead-poses", 0, "--out", tmp_path / "out"], LIVE)
    daemon, sock_dir = None, None
    try:
        _, pid, folder = read_until(proc, "daemon ").split(maxsplit=2)
        daemon, sock_dir = int(pid), Path(folder)
        proc.send_signal(how)
        out, err = proc.communicate(timeout=120)
        assert not wait_gone({daemon}), "the daemon outlived the benchmark"
        if how == signal.SIGTERM:
            assert proc.returncode == 130 and "Traceback" not in err, err
            assert "interrupted: 0 of 1 scenes measured" in err
            assert not sock_dir.exists()  # the rig's socket folder is removed
    finally:
        kill_all(proc, {daemon} if daemon else set())
        if sock_dir is not None:
            shutil.rmtree(sock_dir, ignore_errors=True)


def test_lives_workers_are_named_as_its_children(tmp_path, monkeypatch):
    bench = load_benchmark("live")
    seen = []

    class FakePopen:
        def __init__(self, argv, env=None, **kwargs):
            seen.append(env)

        def wait(self):
            return 0

    monkeypatch.setattr(bench.subprocess, "Popen", FakePopen)
    assert bench.run_to_end(["spadscan", "worker"], tmp_path / "worker.log", {"OMP_NUM_THREADS": "1"}) == 0
    assert seen[0][parent_watch.ENV] == str(os.getpid()) and seen[0]["OMP_NUM_THREADS"] == "1"


def catches_sigint(pid: int) -> bool:
    """Whether `pid` has its own SIGINT handler installed (Python's, once it has started): a Ctrl-C then raises
    KeyboardInterrupt in it, as in a run under way."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    caught = next((line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), "0")
    return bool(int(caught, 16) & (1 << (signal.SIGINT - 1)))


def start_endless_ablation(tmp_path: Path, out: Path) -> subprocess.Popen:
    """The ablation of a tiny scene into `out`, as a terminal's job (a process group of its own), with a real run of
    10^6 steps: it never ends by itself."""
    return start_main("ablation", ["--scenes", tiny_capture(tmp_path), "--out", out, "--steps", 1_000_000,
                                   "--points", 1000, "--parts", "erosion"], "import os\nos.setpgrp()")


def wait_for_run(pid: int, timeout_s: float = 300.0) -> set[int]:
    """The child processes of `pid` once one of them runs with Python's SIGINT handler (at most `timeout_s`:
    generous, for a loaded machine that imports torch twice); AssertionError if none does in time."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        runs = children(pid)
        if any(catches_sigint(p) for p in runs):
            return runs
        time.sleep(0.05)
    raise AssertionError("no run started")


def ctrl_c(proc: subprocess.Popen) -> None:
    """A terminal's Ctrl-C: SIGINT to every process of the foreground job's group (`proc` leads its own)."""
    os.killpg(proc.pid, signal.SIGINT)


@pytest.mark.parametrize("how", [pytest.param(ctrl_c, id="ctrl-c"), *STOPS])
def test_ablations_run_stopped_is_not_run_not_failed(tmp_path, how):
    # A real run, in a child process of the script's worker thread, stopped as a user or a time limit stops it. The
    # run never ends by itself (10^6 steps).
    out = tmp_path / "out"
    proc = start_endless_ablation(tmp_path, out)
    runs: set[int] = set()
    try:
        runs = wait_for_run(proc.pid)
        if callable(how):
            how(proc)
        else:
            proc.send_signal(how)
        stdout, err = proc.communicate(timeout=120)
        assert not wait_gone(runs), "the run outlived the benchmark"
        if how == signal.SIGKILL:
            return  # killed outright, it writes nothing: its run stopped by itself
        assert proc.returncode == 130 and "Traceback" not in err, err
        assert "interrupted" in err and "failed" not in stdout + err, stdout + err
        table = (out / "table.md").read_text()
        assert "| all parts | - |" in table and "| erosion | - |" in table and "failed" not in table, table
        assert json.loads((out / "results.json").read_text()) == {"box": {}}
        assert not list((out / "runs").glob("*.json"))  # the same command runs it again
    finally:
        kill_all(proc, runs)


def state(pid: int) -> str | None:
    """`pid`'s state letter in /proc ('R' running, 'S' sleeping, 'T' stopped, ...), None once it is gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return None


def cpu_ticks(pid: int) -> int:
    """The CPU time `pid` has used, in clock ticks (user and system; 0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return 0
    return int(fields[11]) + int(fields[12])


def wait_until(check, what: str, timeout_s: float = 120.0) -> None:
    """Wait until `check()` holds (at most `timeout_s`: generous, for a loaded machine); AssertionError naming `what`
    if it does not in time."""
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"not in {timeout_s:g} s: {what}")
        time.sleep(0.05)


def ctrl_z(proc: subprocess.Popen) -> None:
    """A terminal's Ctrl-Z: SIGTSTP to every process of the foreground job's group (`proc` leads its own)."""
    os.killpg(proc.pid, signal.SIGTSTP)


def fg_and_ctrl_c(proc: subprocess.Popen, runs: set[int]) -> None:
    """`fg` (SIGCONT to the job's group), then, once the runs use the CPU again, Ctrl-C."""
    ticks = {pid: cpu_ticks(pid) for pid in runs}
    os.killpg(proc.pid, signal.SIGCONT)
    wait_until(lambda: all(state(pid) not in ("T", None) and cpu_ticks(pid) > ticks[pid] for pid in runs),
               "the runs going on after fg")
    ctrl_c(proc)


def kill_job(proc: subprocess.Popen, runs: set[int]) -> None:
    """`kill %1` on a stopped job: SIGTERM, then SIGCONT, to the job's group."""
    os.killpg(proc.pid, signal.SIGTERM)
    os.killpg(proc.pid, signal.SIGCONT)


def kill_9_job(proc: subprocess.Popen, runs: set[int]) -> None:
    """`kill -9 %1` on a stopped job: SIGKILL to the job's group."""
    os.killpg(proc.pid, signal.SIGKILL)


@pytest.mark.parametrize("then", [pytest.param(fg_and_ctrl_c, id="fg-then-ctrl-c"),
                                  pytest.param(kill_job, id="kill"), pytest.param(kill_9_job, id="kill-9")])
def test_ablation_paused_by_ctrl_z_pauses_its_runs(tmp_path, then):
    # Ctrl-Z pauses the whole job, the runs (in process groups of their own) included; fg goes on with them, and the
    # job then ends as one that was never paused. A real run that never ends by itself (10^6 steps).
    out = tmp_path / "out"
    proc = start_endless_ablation(tmp_path, out)
    runs: set[int] = set()
    try:
        runs = wait_for_run(proc.pid)
        ctrl_z(proc)
        wait_until(lambda: all(state(pid) == "T" for pid in {proc.pid, *runs}), "the ablation and its run stopped")
        then(proc, runs)
        stdout, err = proc.communicate(timeout=120)
        assert not wait_gone(runs), "the run outlived the benchmark"
        if then is kill_9_job:
            return  # killed outright while paused, it writes nothing: the kernel hung its paused run up
        assert proc.returncode == 130 and "Traceback" not in err, err
        assert "interrupted" in err and "failed" not in stdout + err, stdout + err
        assert "| all parts | - |" in (out / "table.md").read_text()
    finally:
        kill_all(proc, runs)  # SIGKILL ends a paused process too


def blocked_signals(pid: int) -> int:
    """`pid`'s blocked-signal mask from /proc (bit n - 1 for signal n)."""
    status = Path(f"/proc/{pid}/status").read_text()
    return int(next(line.split()[1] for line in status.splitlines() if line.startswith("SigBlk:")), 16)


def test_ablation_runs_are_started_with_ctrl_z_blocked(tmp_path):
    # A Ctrl-Z between a run's fork and its exec reaches the child while it is still in the ablation's group: the
    # child stopped there, and the thread starting it with it (a vfork child), which holds the lock the pause waits
    # for: the ablation never stopped (seen on a loaded machine). Started with SIGTSTP blocked, the child cannot stop
    # so; a run is paused by SIGSTOP, which no mask blocks.
    out = tmp_path / "out"
    proc = start_endless_ablation(tmp_path, out)
    runs: set[int] = set()
    try:
        runs = wait_for_run(proc.pid)
        wait_until(lambda: all("--one" in Path(f"/proc/{pid}/cmdline").read_text() for pid in runs), "the run's exec")
        assert all(blocked_signals(pid) & (1 << (signal.SIGTSTP - 1)) for pid in runs)
        assert not blocked_signals(proc.pid) & (1 << (signal.SIGTSTP - 1)), "the ablation itself still takes Ctrl-Z"
    finally:
        kill_all(proc, runs)


ERROR_VS_TIME = """
import subprocess, time
real_run = subprocess.run
def run(cmd, *args, **kwargs):
    if cmd[0] == "git":  # the benchmark asks which commit it measures
        return real_run(cmd, *args, **kwargs)
    print("running", flush=True)  # a run that is cut off
    time.sleep(3600)
bench.subprocess.run = run
"""


@pytest.mark.parametrize("how", [pytest.param(signal.SIGINT, id="ctrl-c"), pytest.param(signal.SIGTERM, id="SIGTERM")])
def test_error_vs_time_cut_off_exits_130(tmp_path, how):
    # A table cut off by Ctrl-C or a time limit is told from a whole one by its exit status, as the other benchmarks'.
    capture = tiny_capture(tmp_path)
    out = tmp_path / "out"
    proc = start_main("error_vs_time", ["--scenes", capture, "--budget-s", 60, "--out", out], ERROR_VS_TIME)
    try:
        read_until(proc, "running")
        proc.send_signal(how)
        stdout, err = proc.communicate(timeout=120)
        assert proc.returncode == 130 and "Traceback" not in err, err
        assert "interrupted: the table holds the runs so far" in err
        assert json.loads((out / "results.json").read_text())["results"] == []
    finally:
        kill_all(proc, set())
