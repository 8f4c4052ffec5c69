"""What a run reports says one thing wherever it is read: report.json's `warnings` are the run's warnings, and
report.html, `spadscan worker --status`, the demo and the dashboard show and count those and no others (a run that
did not converge says so there once); a --threads overload is one of them; the progress lines say what their seconds
count, as the summary's 'seconds of training' counts the steps alone."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker import end_of_run
from spadscan.worker.end_of_run import UNCONVERGED, RunFacts
from spadscan.worker.recon.model_api import RunPlan
from spadscan.worker.recon.trainer import PROGRESS_LINES, train
from spadscan.worker.report.report_html import warnings as page_warnings
from spadscan.worker.status_detail import status_lines

pytestmark = pytest.mark.usefixtures("one_thread")

SETTLING = [1.0 + 0.001 * np.cos(i) for i in range(100)]
"""A data term that had all but stopped falling: no 'stopped early' line, yet the model's plateau test had not
said converged."""


def done_row(result) -> SimpleNamespace:
    """A done job's --status row whose result folder is `result`."""
    return SimpleNamespace(state="done", result=str(result), kept=False, notes=[], id="cap-fast", stale=None,
                           error=None)


BUDGET_ENDED = f"{UNCONVERGED} (it ended on its time budget: a larger --budget-s gives it longer)"
STEPS_ENDED = f"{UNCONVERGED} (it ended on its step count: a larger --steps gives it longer)"


def test_a_run_that_did_not_converge_says_so_in_report_json_and_every_reader_counts_it_once(tmp_path):
    lines = end_of_run.warnings(RunFacts("budget", 100, False, SETTLING))
    assert lines == [BUDGET_ENDED], lines
    report = {"preset": "fast", "converged": False, "warnings": lines, "capture_state": "complete"}
    (tmp_path / "report.json").write_text(json.dumps(report))
    assert page_warnings(report) == lines, "the page adds no line of its own beside report.json's"
    said = status_lines(done_row(tmp_path))
    assert "(1 warning below)" in said[0] and said[1:] == [f"warning: {BUDGET_ENDED}"], said


def test_the_unconverged_line_names_what_ended_the_run_and_the_flag_that_gives_it_longer():
    # One line for every reader (the demo adds nothing to it): what ended the run is the run's own.
    assert end_of_run.warnings(RunFacts("steps", 100, False, SETTLING)) == [STEPS_ENDED]
    assert end_of_run.unconverged_line("budget") == BUDGET_ENDED
    assert end_of_run.unconverged_line("something else") == UNCONVERGED


def test_a_line_that_says_why_it_did_not_converge_stands_alone():
    for facts in (RunFacts("budget", 100, False, list(np.linspace(2.0, 1.0, 100))),  # still falling
                  RunFacts("steps", 20, False, [1.0] * 20),  # a rough early state
                  RunFacts("interrupted", 40, False, [1.0 / (i + 1) for i in range(40)])):  # Ctrl-C
        (line,) = end_of_run.warnings(facts)
        assert line != UNCONVERGED and ("converge" in line or "settle" in line), line
    assert end_of_run.warnings(RunFacts("converged", 100, True, SETTLING)) == []
    # A live job's final polish on the step count it chose: too few steps for the plateau test, no line. A final
    # run on the steps the user asked for (`worker --live --steps 3000`), or on a time budget (the demo's final run,
    # from the live fit or the hull), is judged as any run.
    polish = RunFacts("steps", 40, False, [1.0] * 40, continued=True, polish=True)
    assert end_of_run.warnings(polish) == []
    assert end_of_run.warnings(RunFacts("steps", 3000, False, SETTLING * 30, continued=True)) == [STEPS_ENDED]
    assert end_of_run.warnings(RunFacts("budget", 40, False, [1.0] * 40, continued=True)) == [BUDGET_ENDED]
    assert end_of_run.warnings(RunFacts("budget", 100, False, SETTLING, continued=True)) == [BUDGET_ENDED]


def test_the_specks_line_of_a_run_stopped_early_does_not_say_a_longer_run_hardly_changes_it():
    speckled = SimpleNamespace(count=1, share_apart=0.0, specks=91, specks_share=0.026, tunnels=None)
    short = end_of_run.warnings(RunFacts("steps", 20, False, [1.0] * 20, pieces=speckled))
    specks = next(line for line in short if "specks" in line)
    assert "hardly changes" not in specks and "run it longer first" in specks, specks
    assert all(line.endswith("run it longer first)") for line in short[1:]), "as the other doubts of its shape"
    (settled,) = end_of_run.warnings(RunFacts("converged", 100, True, SETTLING, pieces=speckled))
    assert "a longer run hardly changes it: scan closer, or with more signal" in settled, settled


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("consistency")
    mesh = trimesh.creation.box(extents=(0.07, 0.05, 0.09))
    mesh.apply_translation([0.0, 0.0, 0.045])
    poses = fibonacci_hemisphere(6, 0.3, target=(0, 0, 0.05), min_elevation_deg=15)
    return simulate_capture(mesh, sensor_preset("lcspc-sim"), poses, root / "cap",
                            settings=SimSettings(rays_per_zone=512), progress=False)


def test_more_threads_than_cores_is_one_of_the_runs_warnings(capture, tmp_path, monkeypatch):
    import spadscan.worker.reconstruct as reconstruct

    monkeypatch.setattr(reconstruct, "machine_cores", lambda: 1)
    said: list[str] = []
    out = tmp_path / "out"
    report = reconstruct.reconstruct_capture(capture, out, preset="fast", steps=2, device="cpu", progress=False,
                                             threads=2, log=said.append)
    line = "2 CPU threads on 1 cores: OpenMP threads that lose their core stall each other"
    (kept,) = [w for w in json.loads((out / "report.json").read_text())["warnings"] if w.startswith(line)]
    assert kept in report["warnings"] and kept in page_warnings(report)
    top = (out / "report.html").read_text().split("<h2>Summary", 1)[0]
    assert "2 CPU threads on 1 cores" in top, "at the page's top, with the run's other warnings"
    assert [s for s in said if "CPU threads on" in s] == [f"warning: {kept}"], "said once, as the run starts"


def lines_of(capsys, evaluate) -> list[str]:
    """The progress lines of a 10 s budget of 1 s steps (a fake clock), with `evaluate` at its checkpoints."""
    now = [0.0]

    class Step:
        def step(self) -> dict:
            now[0] += 1.0
            return {"loss": 1.0}

    train(Step(), RunPlan(steps=None, budget_s=10.0, seed=0), progress=PROGRESS_LINES, evaluate=evaluate,
          clock=lambda: now[0], cpu_clock=lambda: now[0], desc="reconstruct (fast)")
    return capsys.readouterr().err.splitlines()


def test_the_progress_lines_say_when_their_seconds_count_checkpoint_scoring_too(capsys):
    # The summary's "N steps in X s of training" counts the steps alone (report.json's `seconds`); with a ground
    # truth the budget's seconds on the bar count the checkpoints' scoring as well, and the lines say so.
    scored = lines_of(capsys, evaluate=lambda: {"chamfer_mm": 5.0})
    assert all(" s of training and checkpoint scoring (" in line for line in scored), scored
    plain = lines_of(capsys, evaluate=None)
    assert plain and all(" s of training (" in line for line in plain), plain
