"""A first Ctrl-C while `spadscan reconstruct` trains ends the training and keeps the run (its mesh and report made,
its warnings saying it was stopped); a second one, or one before training began, aborts it keeping nothing."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import pytest
import trimesh

from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker.end_of_run import INTERRUPTED, RunFacts, warnings
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.trainer import train
from spadscan.worker.report.report_html import warnings as page_warnings

pytestmark = pytest.mark.usefixtures("one_thread")


class Falling:
    """A stand-in model whose loss keeps falling: it never converges."""

    def __init__(self):
        self.steps = 0

    def step(self) -> dict:
        self.steps += 1
        return {"loss": 1.0 / self.steps}


def asked_after(calls: int):
    """A stop that says yes from its `calls`-th question on."""
    count = [0]

    def stop() -> bool:
        count[0] += 1
        return count[0] >= calls
    return stop


def test_a_stop_asked_while_training_ends_it_at_the_next_step():
    result = train(Falling(), RunPlan(steps=1000, budget_s=None, seed=0), progress=False, stop=asked_after(4))
    assert (result.stopped_by, result.steps) == ("interrupted", 3)
    first = train(Falling(), RunPlan(steps=1000, budget_s=None, seed=0), progress=False, stop=lambda: True)
    assert (first.stopped_by, first.steps) == ("interrupted", 1), "every run makes at least one step"


def test_a_run_stopped_before_it_converged_says_so_in_its_own_words():
    facts = RunFacts("interrupted", 40, False, [1.0 / (i + 1) for i in range(40)])
    (line,) = warnings(facts)
    assert line.startswith(f"{INTERRUPTED} after 40 step(s), before it converged")
    report = {"converged": False, "warnings": [line]}
    assert page_warnings(report) == [line], "no generic line beside it, in report.json or on the page"
    assert warnings(RunFacts("interrupted", 40, True, [1.0] * 40)) == [], "a fit that had settled is no doubt"


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("ctrl_c")
    mesh = trimesh.creation.box(extents=(0.07, 0.05, 0.09))
    mesh.apply_translation([0.0, 0.0, 0.045])
    poses = fibonacci_hemisphere(6, 0.3, target=(0, 0, 0.05), min_elevation_deg=15)
    return simulate_capture(mesh, sensor_preset("lcspc-sim"), poses, root / "cap",
                            settings=SimSettings(rays_per_zone=512), progress=False)


def test_a_run_whose_training_is_stopped_keeps_its_mesh_and_report(capture, tmp_path):
    from spadscan.worker.reconstruct import reconstruct_capture

    report = reconstruct_capture(capture, tmp_path / "o", steps=100_000, progress=False, stop=asked_after(30))
    assert (report["stopped_by"], report["steps"]) == ("interrupted", 29)
    assert any(w.startswith(INTERRUPTED) for w in report["warnings"])
    assert json.loads((tmp_path / "o" / "report.json").read_text())["stopped_by"] == "interrupted"
    assert (tmp_path / "o" / "mesh.ply").stat().st_size > 0 and (tmp_path / "o" / "report.html").exists()


STAND_IN = """
import signal, sys, time
from spadscan.cli import main
from spadscan.worker import reconstruct

THEN_WAIT = "--then-wait" in sys.argv
LOADING = "--loading" in sys.argv
IGNORED = "--ignored" in sys.argv

def stand_in(capture, out_dir, stop=None, **kwargs):
    out_dir.mkdir(parents=True, exist_ok=True)
    deadline = time.monotonic() + 120  # a bound, not a wait: the test stops it long before
    if LOADING:
        print("loading", flush=True)
        while time.monotonic() < deadline:  # the capture loads: no training has asked the stop yet
            time.sleep(0.01)
    stop()
    print("training", flush=True)
    if IGNORED:  # the test's Ctrl-C has come (a handler would have run during the read): was it heard?
        sys.stdin.readline()
        print("asked" if stop() else "not asked", flush=True)
    while not IGNORED and not stop() and time.monotonic() < deadline:
        time.sleep(0.01)
    print("ended training", flush=True)
    (out_dir / "mesh.ply").write_text("the stopped run's mesh")
    (out_dir / "report.json").write_text("{}")
    while THEN_WAIT and time.monotonic() < deadline:  # the mesh and report take their time: a second Ctrl-C comes
        time.sleep(0.01)
    return {"preset": "fast", "steps": 7, "seconds": 1.0, "wall_seconds": 1.5, "device": "cpu", "converged": False,
            "final_loss": 1.0, "files": ["mesh.ply", "report.json"]}

reconstruct.reconstruct_capture = stand_in
# As a terminal's Ctrl-C finds it, or as a shell script's background job inherits it (ignored).
signal.signal(signal.SIGINT, signal.SIG_IGN if IGNORED else signal.default_int_handler)
sys.exit(main([arg for arg in sys.argv[1:] if arg not in ("--then-wait", "--loading", "--ignored")]))
"""


def _started(tmp_path, *extra):
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "scan.json").write_text("{}")  # a capture folder to the early check; the run a stand-in
    quiet = [] if "--progress" in extra else ["--no-progress"]
    return subprocess.Popen([sys.executable, "-c", STAND_IN, "reconstruct", str(tmp_path / "s"), "--out",
                             str(tmp_path / "out"), "--no-gt", *quiet, *extra],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def ctrl_c_after(tmp_path, lines: list[str], *extra, then: str | None = None) -> tuple[int, str, str]:
    """Run the stand-in with `extra` flags, press Ctrl-C once after each of its output `lines` in turn, give it
    `then` on its stdin, and return (its exit status, the rest of its stdout, its stderr)."""
    proc = _started(tmp_path, *extra)
    try:
        for line in lines:
            assert proc.stdout.readline() == line + "\n"
            proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(then, timeout=60)
    finally:
        proc.kill()
        proc.wait()
    return proc.returncode, out, err


def test_a_first_ctrl_c_while_training_publishes_the_run(tmp_path):
    code, _, err = ctrl_c_after(tmp_path, ["training"])
    assert code == 0, err
    assert "stopping: training ends at its next step" in err and "Ctrl-C again aborts, keeping nothing" in err
    assert (tmp_path / "out" / "mesh.ply").read_text() == "the stopped run's mesh"


def test_with_a_progress_bar_the_stop_is_said_on_a_line_of_its_own(tmp_path):
    code, _, err = ctrl_c_after(tmp_path, ["training"], "--progress")
    assert code == 0 and "\nspadscan reconstruct: stopping: training ends" in err, err


def test_a_second_ctrl_c_aborts_keeping_nothing(tmp_path):
    code, _, err = ctrl_c_after(tmp_path, ["training", "ended training"], "--then-wait")
    assert code == 130 and err.strip().splitlines()[-1] == "spadscan: interrupted", err
    assert not (tmp_path / "out").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["s"], "no hidden folder left"


def test_a_ctrl_c_before_training_began_aborts_at_once(tmp_path):
    code, _, err = ctrl_c_after(tmp_path, ["loading"], "--loading")
    assert code == 130 and "stopping:" not in err, err
    assert [p.name for p in tmp_path.iterdir()] == ["s"], "nothing kept, no hidden folder left"


def test_a_run_started_with_ctrl_c_ignored_keeps_ignoring_it(tmp_path):
    """A shell script's background job (`spadscan reconstruct ... &`) inherits SIGINT ignored: a Ctrl-C meant for
    the script must not end its training."""
    code, out, err = ctrl_c_after(tmp_path, ["training"], "--ignored", then="go\n")
    assert code == 0 and out.splitlines()[0] == "not asked", (out, err)
    assert "stopping:" not in err
