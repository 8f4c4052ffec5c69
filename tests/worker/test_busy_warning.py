"""The busy-machine warning reads what a CPU run lost to other processes from its threads' waits for a core
(worker/cpu_wait.py), not from its CPU time, which counts OpenMP threads spinning while a partner waits for its core
as work. Every figure here comes from injected readers and clocks: nothing depends on the machine's load."""

from __future__ import annotations

import threading

import pytest

from spadscan.worker.cpu_wait import ThreadWaits, lost_seconds, read_threads
from spadscan.worker.end_of_run import RunFacts, cpu_share, cpu_wait, lost_share, pace_share, warnings
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.trainer import train

FLAT = [1.0] * 100  # a data term that settled: the only warning left to give is the busy machine's

# Measured on a 2-core machine (docs/end_of_run.md), as shares of training's wall time, [on a CPU, waiting for one]:
# two threads that spin at their barriers beside one CPU-bound process (16x fewer steps than alone, their CPU time
# 0.96 of a core) ...
SPINNING = {"main": [0.49, 0.48], "helpers": [[0.47, 0.47]]}
# ... and two passive threads beside two, whose helper sleeps between the operations it is woken for (1.7x fewer;
# their CPU time 0.58 of a core).
PASSIVE = {"main": [0.42, 0.45], "helpers": [[0.16, 0.19]]}


def scaled(times: dict, wall_s: float) -> dict:
    return {"main": [x * wall_s for x in times["main"]], "helpers": [[x * wall_s for x in h] for h in times["helpers"]]}


def busy_lines(facts: RunFacts) -> list[str]:
    return [w for w in warnings(facts) if w.startswith("the machine was busy")]


# ---- the rule ------------------------------------------------------------------------------------------------

def test_spinning_threads_that_waited_for_their_cores_are_called_starved_though_their_cpu_time_reads_a_core():
    wall = 20.0
    facts = RunFacts("budget", 150, True, FLAT, cpu_seconds=0.96 * wall, wall_seconds=wall,
                     thread_times=scaled(SPINNING, wall))
    assert cpu_share(facts) == pytest.approx(0.96)
    assert lost_share(facts) == pytest.approx(0.48 + 0.47)
    (line,) = busy_lines(facts)
    assert "waited for CPU cores for 95 % of its training" in line and "about 20x slower" in line, line
    assert "(150 steps)" in line and "more threads than cores" in line and "`--threads 1`" in line, line
    assert "0.96 of a core" in line and "spun" in line, "the CPU time it had is explained, not hidden"
    figures = cpu_wait(facts)
    assert figures["lost_s"] == pytest.approx(lost_share(facts) * wall)
    assert figures["slowdown"] == pytest.approx(1 / (1 - lost_share(facts)))
    assert figures["threads"] == facts.thread_times


def test_the_waits_of_a_helper_asleep_most_of_the_time_are_not_the_runs():
    wall = 10.0
    facts = RunFacts("budget", 150, True, FLAT, cpu_seconds=0.58 * wall, wall_seconds=wall,
                     thread_times=scaled(PASSIVE, wall))
    assert lost_share(facts) == pytest.approx(0.45), "the stepping thread's wait alone"
    assert busy_lines(facts) == []
    awake = {"main": PASSIVE["main"], "helpers": [[0.16, 0.19], [0.30, 0.25]]}  # a third thread, runnable 55 %
    facts = RunFacts("budget", 150, True, FLAT, cpu_seconds=0.88 * wall, wall_seconds=wall,
                     thread_times=scaled(awake, wall))
    assert lost_share(facts) == pytest.approx(0.70)
    (line,) = busy_lines(facts)
    assert "for 70 % of its training" in line and "about 3x slower" in line, line


def test_one_thread_that_waited_half_its_time_or_more_is_starved_by_its_wait_alone():
    wall = 10.0
    for wait, starved in ((0.45, False), (0.55, True)):
        facts = RunFacts("budget", 100, True, FLAT, cpu_seconds=(1 - wait) * wall, wall_seconds=wall,
                         thread_times={"main": [(1 - wait) * wall, wait * wall], "helpers": []})
        assert pace_share(facts) == (pytest.approx(1 - wait), True)
        assert bool(busy_lines(facts)) is starved
    (line,) = busy_lines(facts)
    assert "for 55 % of its training" in line and "about 2x slower" in line and "spun" not in line, line
    assert "more threads" not in line and "--threads" not in line, "one thread: only other processes held them"


def test_without_the_threads_waits_the_cpu_time_judges_as_before():
    facts = RunFacts("budget", 100, True, FLAT, cpu_seconds=2.0, wall_seconds=10.0)
    assert pace_share(facts) == (pytest.approx(0.2), False) and cpu_wait(facts) is None
    (line,) = busy_lines(facts)
    assert "this run had 0.20 of a CPU core" in line and "5x slower than it would alone (100 steps)" in line


def test_only_a_cpu_run_stopped_by_its_budget_is_called_starved():
    times = scaled(SPINNING, 10.0)
    for stop, device in (("converged", "cpu"), ("steps", "cpu"), ("budget", "cuda")):
        facts = RunFacts(stop, 100, True, FLAT, device=device, cpu_seconds=9.6, wall_seconds=10.0,
                         thread_times=times)
        assert busy_lines(facts) == [], (stop, device)


def test_the_lost_seconds_stay_within_the_wall_time_and_refuse_nonsense():
    saturated = {"main": [1.0, 9.0], "helpers": [[1.0, 9.0], [1.0, 9.0]]}
    assert lost_seconds(saturated, 10.0) == 10.0
    facts = RunFacts("budget", 100, True, FLAT, cpu_seconds=3.0, wall_seconds=10.0, thread_times=saturated)
    assert pace_share(facts) == (0.01, True) and cpu_wait(facts)["slowdown"] == pytest.approx(100.0)
    (line,) = busy_lines(facts)
    assert "about 100x slower" in line, "waits that overlap: the figure stays finite"
    for bad in (None, {}, {"main": [1.0]}, {"main": [1.0, float("nan")]}, {"main": [1.0, -1.0]},
                {"main": [1.0, 1.0], "helpers": [["x", 1.0]]}):
        assert lost_seconds(bad, 10.0) is None, bad
    for wall in (0.0, -1.0, float("inf"), float("nan")):
        assert lost_seconds({"main": [1.0, 1.0]}, wall) is None, wall
    facts = RunFacts("budget", 100, True, FLAT, cpu_seconds=9.0, wall_seconds=10.0,
                     thread_times={"main": [1.0, float("nan")]})
    assert pace_share(facts) == (pytest.approx(0.9), False), "unusable waits: the CPU time judges"


def test_statistics_this_kernel_does_not_keep_read_as_unknown_not_as_an_idle_machine():
    zeros = {"main": [0.0, 0.0], "helpers": []}  # a kernel without scheduler statistics
    assert lost_seconds(zeros, 10.0) is None
    facts = RunFacts("budget", 100, True, FLAT, cpu_seconds=2.0, wall_seconds=10.0, thread_times=zeros)
    assert pace_share(facts) == (pytest.approx(0.2), False) and cpu_wait(facts) is None
    (line,) = busy_lines(facts)
    assert "this run had 0.20 of a CPU core" in line, "the CPU time judges, and says so"


# ---- reading the threads ----------------------------------------------------------------------------------------

def test_the_scheduler_statistics_are_read_per_thread_in_seconds(tmp_path):
    for tid, line in ((101, "2500000000 500000000 40\n"), (102, "1000000 0 3\n")):
        (tmp_path / str(tid)).mkdir()
        (tmp_path / str(tid) / "schedstat").write_text(line)
    (tmp_path / "103").mkdir()  # a thread that ended between the listing and the read
    assert read_threads(tmp_path) == {101: (2.5, 0.5), 102: (0.001, 0.0)}
    (tmp_path / "104").mkdir()
    (tmp_path / "104" / "schedstat").write_text("garbled\n")
    assert read_threads(tmp_path) is None
    assert read_threads(tmp_path / "missing") is None


class Threads:
    """Cumulative times of a process's threads, as `read_threads` gives them, moved on by hand."""

    def __init__(self):
        self.times: dict[int, tuple[float, float]] | None = {}

    def add(self, tid: int, run: float, wait: float) -> None:
        r, w = self.times.get(tid, (0.0, 0.0))
        self.times[tid] = (r + run, w + wait)

    def __call__(self):
        return None if self.times is None else dict(self.times)


def test_thread_waits_sum_the_stretches_and_count_a_thread_born_in_one_from_its_start():
    threads = Threads()
    threads.add(1, 5.0, 5.0)  # before the first stretch: not the run's
    waits = ThreadWaits(threads, main=1)
    waits.resume()
    threads.add(1, 1.0, 2.0)
    threads.add(7, 0.5, 0.25)  # an OpenMP worker started in the stretch
    waits.pause()
    threads.add(1, 9.0, 9.0)  # a checkpoint's evaluation: not a step
    threads.add(8, 3.0, 3.0)
    waits.resume()
    threads.add(1, 1.0, 1.0)
    del threads.times[8]  # a thread that ended: what it did before the stretch is no part of it
    waits.pause()
    assert waits.summary() == {"main": [2.0, 3.0], "helpers": [[0.5, 0.25]]}


def test_thread_waits_are_unknown_once_a_reading_fails_and_the_stepping_thread_is_the_callers():
    threads = Threads()
    threads.add(threading.get_native_id(), 1.0, 1.0)
    waits = ThreadWaits(threads)
    assert waits.summary() is None, "no stretch yet"
    waits.resume()
    threads.add(threading.get_native_id(), 1.0, 0.5)
    waits.pause()
    assert waits.summary() == {"main": [1.0, 0.5], "helpers": []}
    threads.times = None
    waits.resume()
    waits.pause()
    assert waits.summary() is None, "a partial sum would read as an idle machine"


class Model:
    """A model whose step moves the threads' clock: each step 0.1 s on a CPU, 0.3 s waiting for one."""

    def __init__(self, threads: Threads, tid: int):
        self.threads, self.tid = threads, tid

    def step(self) -> dict:
        self.threads.add(self.tid, 0.1, 0.3)
        return {"loss": 1.0}


def test_training_counts_its_steps_waits_and_not_its_checkpoints():
    threads, tid = Threads(), threading.get_native_id()
    ticks = iter(range(10_000))

    def evaluate() -> dict:
        threads.add(tid, 2.0, 7.0)  # an evaluation that waited long: no step's
        return {}

    waits = ThreadWaits(threads)
    result = train(Model(threads, tid), RunPlan(steps=10, budget_s=None, seed=0), checkpoints=5, evaluate=evaluate,
                   progress=False, clock=lambda: float(next(ticks)), cpu_clock=lambda: 0.0, waits=waits)
    assert result.steps == 10 and len(result.trace) == 6
    assert waits.summary()["main"] == [pytest.approx(1.0), pytest.approx(3.0)]


# ---- a whole run -------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def box_capture(tmp_path_factory):
    import trimesh

    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, simulate_capture

    mesh = trimesh.creation.box(extents=(0.07, 0.05, 0.09)).apply_translation([0.0, 0.0, 0.045])
    poses = fibonacci_hemisphere(12, 0.3, target=(0, 0, 0.05), min_elevation_deg=15)
    return simulate_capture(mesh, sensor_preset("lcspc-sim"), poses, tmp_path_factory.mktemp("box") / "box",
                            settings=SimSettings(rays_per_zone=256), progress=False)


class Ticking:
    """A wall clock that moves 50 ms at every reading; the CPU clock and the threads' times follow it at fixed
    shares: a time budget runs out after a fixed number of steps, however busy the real machine."""

    def __init__(self, cpu: float, times: dict):
        self.now, self.cpu_share, self.shares = 0.0, cpu, times
        self.main = threading.get_native_id()

    def __call__(self) -> float:
        self.now += 0.05
        return self.now

    def cpu(self) -> float:
        return self.cpu_share * self.now

    def threads(self) -> dict:
        # The trainer reads the wall clock twice a step and times the step by the second: a step's wall seconds are
        # half what the clock moved.
        steps_s = self.now / 2
        (run, wait), (helper,) = self.shares["main"], self.shares["helpers"]
        return {self.main: (run * steps_s, wait * steps_s), -1: (helper[0] * steps_s, helper[1] * steps_s)}


def test_a_run_whose_spinning_threads_waited_for_their_cores_says_the_machine_was_busy(box_capture, tmp_path):
    from spadscan.worker.reconstruct import reconstruct_capture

    clock = Ticking(cpu=0.96, times=SPINNING)
    report = reconstruct_capture(box_capture, tmp_path / "spun", budget_s=30.0, progress=False, device="cpu",
                                 threads=1, overrides={"mesh_resolution": 32, "early_stop": False}, clock=clock,
                                 cpu_clock=clock.cpu, thread_reader=clock.threads)
    assert report["stopped_by"] == "budget"
    (line,) = [w for w in report["warnings"] if w.startswith("the machine was busy")]
    assert "for 95 % of its training" in line and "about 20x slower" in line, line
    assert report["cpu_cores_used"] == pytest.approx(0.96, abs=0.01), "the key other tools read stays"
    assert report["cpu_wait"]["lost_share"] == pytest.approx(0.95, abs=0.01)

    quiet = Ticking(cpu=0.58, times=PASSIVE)
    report = reconstruct_capture(box_capture, tmp_path / "passive", budget_s=30.0, progress=False, device="cpu",
                                 threads=1, overrides={"mesh_resolution": 32, "early_stop": False}, clock=quiet,
                                 cpu_clock=quiet.cpu, thread_reader=quiet.threads)
    assert not any(w.startswith("the machine was busy") for w in report["warnings"]), report["warnings"]
    assert report["cpu_wait"]["lost_share"] < 0.5


def test_a_run_beside_other_workers_jobs_names_them_and_records_them(box_capture, tmp_path, monkeypatch):
    from spadscan.worker.cpu_wait import MACHINE_JOBS_ENV
    from spadscan.worker.reconstruct import reconstruct_capture

    def run(name: str, value: str) -> tuple[dict, list[str]]:
        monkeypatch.setenv(MACHINE_JOBS_ENV, value)  # as the worker sets it in its job's environment
        clock, said = Ticking(cpu=0.96, times=SPINNING), []
        report = reconstruct_capture(box_capture, tmp_path / name, budget_s=30.0, progress=False, device="cpu",
                                     threads=1, overrides={"mesh_resolution": 32, "early_stop": False}, clock=clock,
                                     cpu_clock=clock.cpu, thread_reader=clock.threads, log=said.append)
        return report, said

    report, _ = run("beside", "2")
    assert report["machine_jobs"] == 2
    (line,) = [w for w in report["warnings"] if w.startswith("the machine was busy")]
    assert ("among them up to 2 job process(es) of other workers on this host, beside which this run kept the "
            "threads it was given") in line, "--threads 1: the run's threads did not count them"
    assert "run fewer job processes on this host" in line and "stop other work" not in line, line
    report, said = run("garbled", "two")
    assert report["machine_jobs"] is None
    assert f"warning: {MACHINE_JOBS_ENV}='two' is not a whole number" in "\n".join(said), said
    (line,) = [w for w in report["warnings"] if w.startswith("the machine was busy")]
    assert "stop other work" in line and "other workers" not in line, "ignored: the line as before"


def test_an_overrun_says_what_the_threads_lost_not_the_cpu_time_that_spinning_fills():
    wall = 20.0
    facts = RunFacts("budget", 150, True, FLAT, cpu_seconds=0.96 * wall, wall_seconds=wall, budget_s=30.0,
                     elapsed_s=45.0, thread_times=scaled(SPINNING, wall))
    (line,) = [w for w in warnings(facts) if w.startswith("the run took")]
    assert "its threads waited for CPU cores for 95 % of its training" in line and "of a CPU core" not in line, line
    unknown = RunFacts("budget", 150, True, FLAT, cpu_seconds=0.6 * wall, wall_seconds=wall, budget_s=30.0,
                       elapsed_s=45.0)
    (line,) = [w for w in warnings(unknown) if w.startswith("the run took")]
    assert "it had 0.60 of a CPU core while training" in line, "without the waits, the CPU time as before"
