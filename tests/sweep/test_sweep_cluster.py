"""`spadscan sweep` on a real Dask cluster: two workers on loopback, one point that fails, one worker killed in the
middle of a point. Every other point finishes exactly once, the killed one runs again on the other worker, and a
re-run runs only the failed point. The embedded LocalCluster path runs the same sweep."""

from __future__ import annotations

import csv
import json
import os
import re
import time
from collections import Counter
from pathlib import Path

import pytest

from sweep_helpers import FAILING_POWER, spadscan

from spadscan.sweep.plan import make_plan
from spadscan.sweep.spec import load_spec

pytestmark = pytest.mark.slow


def read_log(out: Path) -> list[dict]:
    path = out / "log.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.endswith("}")]


def wait_for(condition, deadline_s: float, what: str, proc=None):
    end = time.monotonic() + deadline_s
    while True:
        value = condition()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"the sweep ended before {what}: rc {proc.returncode}")
        if time.monotonic() > end:
            raise AssertionError(f"no {what} within {deadline_s} s")
        time.sleep(0.05)


def test_two_workers_one_killed_mid_point_one_point_failing(dask_cluster, tiny_sweep, tmp_path):
    import subprocess
    import sys

    plan = make_plan(load_spec(tiny_sweep))
    failing = {pid for pid, t in plan.points.items() if t.params["power"] == FAILING_POWER}
    assert len(plan.points) == 3 and len(failing) == 1
    out = tmp_path / "out"
    log_file = open(tmp_path / "sweep.out", "w")
    sweep = subprocess.Popen([sys.executable, "-m", "spadscan.cli", "sweep", str(tiny_sweep), "--out", str(out),
                              "--scheduler", dask_cluster.address, "--no-progress"],
                             stdout=log_file, stderr=subprocess.STDOUT, text=True)
    try:
        # Kill the worker that is reconstructing a point that would succeed, while it reconstructs.
        def reconstructing():
            return next((e for e in read_log(out) if e["event"] == "stage" and e["stage"] == "fast"
                         and e["point"] not in failing), None)

        victim = wait_for(reconstructing, 300, "point reaching its reconstruction", sweep)
        dask_cluster.kill(victim["name"])
        assert sweep.wait(timeout=400) == 0, (tmp_path / "sweep.out").read_text()
    finally:
        if sweep.poll() is None:
            sweep.kill()
            sweep.wait()
        log_file.close()
    output = (tmp_path / "sweep.out").read_text()
    events = read_log(out)
    killed = victim["point"]
    finished = Counter(e["point"] for e in events if e["event"] in ("done", "failed"))
    starts = Counter(e["point"] for e in events if e["event"] == "start")
    assert not any(e["event"] in ("done", "failed") and e["name"] == victim["name"] and e["point"] == killed
                   for e in events), "the point ended before its worker was killed: the kill came too late"
    # Every point ended exactly once; the killed one was started twice, the second time on the other worker.
    assert finished == {pid: 1 for pid in plan.points}, events
    assert starts[killed] == 2 and all(starts[p] == 1 for p in plan.points if p != killed), starts
    second = [e for e in events if e["event"] == "start" and e["point"] == killed][1]
    assert second["name"] != victim["name"]
    results = {pid: json.loads((out / "points" / f"{pid}.json").read_text()) for pid in plan.points}
    assert results[killed]["status"] == "done" and results[killed]["worker"]["name"] == second["name"]
    for pid, result in results.items():
        if pid in failing:
            # No photon comes back: every method fails for that one cause, said once, naming no temporary folder.
            assert result["status"] == "failed" and result["reason"].startswith("every method: "), result["reason"]
            assert "\n" not in result["reason"] and ".running-" not in result["reason"]
        else:
            assert result["status"] == "done", result["reason"]
            assert all(m["status"] == "done" and m["chamfer_mm"] > 0 for m in result["methods"].values())
    assert "3 points: 0 done earlier, 3 run now (2 done, 1 failed)" in output, output
    rows = (out / "results.csv").read_text().splitlines()
    assert len(rows) == 1 + 4  # a header and the four grid entries (the base point sits on both axes)

    # A re-run runs the failed point alone.
    before = len(events)
    rerun = spadscan("sweep", str(tiny_sweep), "--out", str(out), "--scheduler", dask_cluster.address,
                     "--no-progress")
    assert rerun.returncode == 0, rerun.stderr
    new = read_log(out)[before:]
    assert {e["point"] for e in new if e["event"] == "start"} == failing, new
    assert "3 points: 2 done earlier, 1 run now (0 done, 1 failed)" in rerun.stdout, rerun.stdout


def pid_alive(pid: int) -> bool:
    import os

    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    state = Path(f"/proc/{pid}/stat")
    return not (state.exists() and state.read_text().rsplit(")", 1)[1].split()[0] == "Z")


def test_local_cluster_stops_cleanly_and_resumes_where_it_stopped(tiny_sweep, tmp_path):
    import signal
    import subprocess
    import sys

    out = tmp_path / "out"
    plan = make_plan(load_spec(tiny_sweep))
    sweep = subprocess.Popen([sys.executable, "-m", "spadscan.cli", "sweep", str(tiny_sweep), "--out", str(out),
                              "--workers", "2", "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    try:
        wait_for(lambda: any(e["event"] == "done" for e in read_log(out)), 300, "point done", sweep)
        sweep.send_signal(signal.SIGTERM)  # a service stop, a time limit: as Ctrl-C
        _, err = sweep.communicate(timeout=120)
    finally:
        if sweep.poll() is None:
            sweep.kill()
            sweep.wait()
    assert sweep.returncode == 130, err
    assert "local cluster: 2 worker processes" in err and "interrupted" in err
    assert "Traceback" not in err and "leaked" not in err, err
    events = read_log(out)
    workers = {e["pid"] for e in events if "pid" in e}
    wait_for(lambda: not any(pid_alive(p) for p in workers), 60, "worker processes ending with their sweep")
    # The points' files are the truth (a point may end after the client stopped listening to its events).
    done = {p for p in plan.points if json.loads((out / "points" / f"{p}.json").read_text()
                                                  if (out / "points" / f"{p}.json").exists() else "{}").get("status")
            == "done"}
    assert {e["point"] for e in events if e["event"] == "done"} <= done and done
    with open(out / "results.csv", newline="") as f:  # gathered on the way out, not only at a sweep's end
        gathered = {row["point"] for row in csv.DictReader(f)}
    assert {e["point"] for e in events if e["event"] == "done"} <= gathered, gathered

    resumed = spadscan("sweep", str(tiny_sweep), "--out", str(out), "--workers", "2", "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    assert f"3 points: {len(done)} done earlier, {3 - len(done)} run now" in resumed.stdout, resumed.stdout
    assert "failed: builtin:sphere power=1e-07" in resumed.stdout
    started = Counter(e["point"] for e in read_log(out)[len(events):] if e["event"] == "start")
    assert set(started) == set(plan.points) - done and set(started.values()) == {1}

    before = len(read_log(out))
    again = spadscan("sweep", str(tiny_sweep), "--out", str(out), "--workers", "1", "--no-progress")
    assert again.returncode == 0, again.stderr
    assert "3 points: 2 done earlier, 1 run now (0 done, 1 failed)" in again.stdout, again.stdout
    rerun = [e["point"] for e in read_log(out)[before:] if e["event"] == "start"]
    assert [plan.points[p].params["power"] for p in rerun] == [FAILING_POWER]
    assert not list((out / "work").iterdir())  # the interrupted points' work folders went with the next run


def test_ctrl_c_in_the_terminal_stops_the_sweep_in_one_line(tiny_sweep, tmp_path):
    """A terminal's Ctrl-C reaches the whole process group, the cluster's workers too: the sweep still ends in its
    own line, with no worker's traceback or warning, and leaves no worker behind."""
    import signal
    import subprocess
    import sys

    out = tmp_path / "out"
    sweep = subprocess.Popen([sys.executable, "-m", "spadscan.cli", "sweep", str(tiny_sweep), "--out", str(out),
                              "--workers", "2", "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, start_new_session=True)
    try:
        wait_for(lambda: any(e["event"] == "start" for e in read_log(out)), 300, "a point started", sweep)
        os.killpg(sweep.pid, signal.SIGINT)
        _, err = sweep.communicate(timeout=120)
    finally:
        if sweep.poll() is None:
            os.killpg(sweep.pid, signal.SIGKILL)
            sweep.wait()
    assert sweep.returncode == 130, err
    assert "interrupted; the points finished are kept in" in err, err
    assert "Traceback" not in err and "leaked" not in err and "distributed" not in err, err
    workers = {e["pid"] for e in read_log(out) if "pid" in e}
    wait_for(lambda: not any(pid_alive(p) for p in workers), 60, "worker processes ending with their sweep")


KILLER = """
import sys
from pathlib import Path

import dask

from spadscan.sweep.plan import make_plan
from spadscan.sweep.runner import run_sweep
from spadscan.sweep.spec import load_spec


def dies_every_time(task, out, device, keep):
    import os
    import time

    from distributed import get_client, get_worker

    # Once its nanny knows its address, which it reads moments after the worker starts (the restarted worker gets the
    # point at once): the ending of a worker that died before then is not known, and its point says "died".
    worker = get_worker()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        known = get_client().run(lambda dask_worker: dask_worker.worker_address, workers=[worker.address],
                                 nanny=True)
        if known.get(worker.address) == worker.address:
            break
        time.sleep(0.05)
    os._exit(1)  # takes its worker down with it


if __name__ == "__main__":
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        summary = run_sweep(make_plan(load_spec(sys.argv[1])), Path(sys.argv[2]), workers=1, progress=False,
                            point=dies_every_time)
    print(summary.ran, summary.done, len(summary.failed))
"""


def test_a_point_that_kills_every_worker_it_runs_on_is_recorded_as_failed(tmp_path):
    import subprocess
    import sys

    one_point = tmp_path / "one.toml"
    one_point.write_text('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nviews = 4\n')
    script = tmp_path / "killer.py"
    script.write_text(KILLER)
    run = subprocess.run([sys.executable, str(script), str(one_point), str(tmp_path / "out")], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.split() == ["1", "0", "1"]
    for task in make_plan(load_spec(one_point)).points.values():
        stored = json.loads((tmp_path / "out" / "points" / f"{task.id}.json").read_text())
        assert stored["status"] == "failed"
        # The embedded cluster's nannies report how their workers ended: here the exit code.
        assert re.fullmatch(r"the worker running it died each time it was tried \(2 workers; the last exited with "
                            r"code 1\); their logs say why \(the last: worker \d+, pid \d+, writing to this "
                            r"command's stderr\)", stored["reason"]), stored["reason"]


SECOND_CTRL_C = """
import signal
import sys
from pathlib import Path

from spadscan.sweep.plan import make_plan
from spadscan.sweep.runner import run_sweep
from spadscan.sweep.spec import load_spec


def ends_during_the_close(task, out, device, keep):
    import os
    import time

    from distributed import get_worker
    from distributed.core import Status

    from spadscan.sweep.store import SweepDir

    out = Path(out)
    client = int((out.parent / "client.pid").read_text())
    os.kill(client, signal.SIGINT)  # Ctrl-C: the client closes the cluster, which asks this worker to stop
    worker = get_worker()
    deadline = time.monotonic() + 120
    while worker.status == Status.running and time.monotonic() < deadline:
        time.sleep(0.01)
    os.kill(client, signal.SIGINT)  # a second Ctrl-C, while the cluster closes
    # The point ends once results.csv is gathered (if it is gathered while the point runs), else after a while
    # well within the time a closing worker gives its task (4 s).
    deadline = time.monotonic() + 1.5
    while not (out / "results.csv").exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    SweepDir(out).write_point({"id": task.id, "status": "done", "reason": None, "params": task.params,
                               "methods": {}})
    return {"id": task.id, "status": "done", "reason": None, "seconds": 0.0, "worker": None}


if __name__ == "__main__":
    signal.signal(signal.SIGINT, signal.default_int_handler)
    out = Path(sys.argv[2])
    (out.parent / "client.pid").write_text(str(__import__("os").getpid()))
    try:
        run_sweep(make_plan(load_spec(sys.argv[1])), out, workers=1, progress=False, point=ends_during_the_close)
    except KeyboardInterrupt:
        print("interrupted")
"""


def test_a_point_that_ends_while_the_cluster_closes_after_ctrl_c_is_in_results_csv(tmp_path):
    """A second Ctrl-C (a terminal's, or `timeout`'s signal to its process group) that came while the cluster closed
    broke off the close: results.csv was gathered while the workers still ran, and missed the points they finished
    after it."""
    import subprocess
    import sys

    one_point = tmp_path / "one.toml"
    one_point.write_text('[sweep]\nscenes = ["builtin:sphere"]\n[base]\nviews = 4\n')
    script = tmp_path / "second_ctrl_c.py"
    script.write_text(SECOND_CTRL_C)
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, str(script), str(one_point), str(out)], capture_output=True, text=True,
                         timeout=300)
    assert run.stdout.split() == ["interrupted"], (run.stdout, run.stderr[-3000:])
    (point,) = make_plan(load_spec(one_point)).points
    assert json.loads((out / "points" / f"{point}.json").read_text())["status"] == "done"
    with open(out / "results.csv", newline="") as f:
        assert [row["point"] for row in csv.DictReader(f)] == [point]
