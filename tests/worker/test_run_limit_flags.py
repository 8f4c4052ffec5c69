"""The run limits (worker/jobs.run_limits_problem: a time budget of at most a week, at most 10,000,000 steps) are
refused by `reconstruct`, `worker` and `demo` alike, in one line that names the flag at fault, and a budget that is
no finite number (1e309 overflows to infinity; nan) is said to be one, not echoed as "inf" or "nan"."""

from __future__ import annotations

import pytest

from spadscan.cli import main as cli_main
from spadscan.demo import Processes

from test_watcher import make_scan

NOT_FINITE = "--budget-s: time budget is not a finite number of seconds: it must be > 0 and at most 604800 (a week)"

CASES = [
    (["--budget-s", "1e309"], NOT_FINITE),
    (["--budget-s", "nan"], NOT_FINITE),
    (["--budget-s", "1e9"], "--budget-s: time budget 1000000000.0 s must be a number of seconds > 0 and at most "
                            "604800 (a week)"),
    (["--steps", str(10**8)], "--steps: steps 100000000 must be an integer in [1, 10,000,000]"),
    (["--seed", "-1"], "--seed: seed -1 must be an integer in [0, 9223372036854775807]"),
]


def refusal(capsys) -> str:
    """The one line a refused command printed, without its 'spadscan: error: ' prefix."""
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert err.startswith("spadscan: error: "), err
    return err.removeprefix("spadscan: error: ")


@pytest.mark.parametrize("argv, message", CASES)
def test_reconstruct_names_the_flag(tmp_path, capsys, argv, message):
    make_scan(tmp_path, "s")
    assert cli_main(["reconstruct", str(tmp_path / "s"), "--out", str(tmp_path / "out"), "--no-progress",
                     *argv]) == 1
    assert refusal(capsys) == message
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, message", CASES)
def test_worker_names_the_flag(tmp_path, capsys, argv, message):
    make_scan(tmp_path, "s")
    assert cli_main(["worker", "--root", str(tmp_path), "--once", *argv]) == 1
    assert refusal(capsys) == message
    assert not (tmp_path / ".queue").exists(), "nothing is queued with a refused option"


@pytest.mark.parametrize("argv", [["--retry-failed"], ["--redo", "s-fast"]])
def test_worker_requeues_name_the_flag(tmp_path, capsys, argv):
    make_scan(tmp_path, "s")
    (tmp_path / ".queue").mkdir()
    assert cli_main(["worker", "--root", str(tmp_path), *argv, "--budget-s", "1e309"]) == 1
    assert refusal(capsys) == NOT_FINITE


@pytest.mark.parametrize("value", ["1e309", "nan"])
def test_demo_says_a_budget_that_is_no_finite_number(tmp_path, capsys, monkeypatch, value):
    def start(self, name, argv, log):
        raise AssertionError(f"the demo started {name} although its budget is refused")

    monkeypatch.setattr(Processes, "start", start)
    assert cli_main(["demo", "--out", str(tmp_path / "demo"), "--budget-s", value]) == 1
    assert refusal(capsys) == NOT_FINITE
    assert not (tmp_path / "demo").exists()
