"""`spadscan reconstruct --out CAPTURE/recon/JOB --overwrite` over a worker job's result: the job's own files (job.json,
job.log, ground_truth.ply, the queue's .complete marker) go with the result they described, instead of standing beside
the new mesh as if they had made it."""

from __future__ import annotations

import json
import os
import time

import pytest

from spadscan.protocol.errors import ConfigError
from spadscan.worker.jobs import COMPLETE
from spadscan.worker.outputs import ASIDE_DIR, check_ground_truth_kept, previous_result, replacing_result

from test_reconstruct_cli import _error_lines, _recon, capture_and_gt  # noqa: F401 (a fixture)

pytestmark = pytest.mark.usefixtures("one_thread")

JOB_OWN = {"job.json": json.dumps({"id": "cap-fast", "steps": 30}), "job.log": "the job's log",
           "ground_truth.ply": "the scene as scanned", COMPLETE: json.dumps({"job": "cap-fast", "token": "0" * 16})}


def _job_result(out):
    """A worker job's published result in `out` (an hour old), and the user's own notes beside it."""
    out.mkdir(parents=True)
    files = {"mesh.ply": "the job's mesh", "report.html": "the job's page",
             "report.json": json.dumps({"steps": 30, "files": ["mesh.ply", "report.html", "report.json"]}),
             **JOB_OWN, "notes.txt": "the user's own notes"}
    for name, text in files.items():
        (out / name).write_text(text)
    an_hour_ago = time.time() - 3600
    for path in out.iterdir():
        os.utime(path, (an_hour_ago, an_hour_ago))
    return files


def _files(out):
    return {p.name: p.read_text(errors="replace") for p in out.iterdir() if p.is_file()}


def test_a_job_results_own_files_are_part_of_the_result_an_overwrite_replaces(tmp_path):
    before = _job_result(tmp_path / "out")
    assert previous_result(tmp_path / "out") == set(before) - {"notes.txt"}
    lines = []
    with replacing_result(tmp_path / "out", lines.append):
        (tmp_path / "out" / "mesh.ply").write_text("the new mesh")
        (tmp_path / "out" / "report.json").write_text("{}")
    assert _files(tmp_path / "out") == {"mesh.ply": "the new mesh", "report.json": "{}",
                                         "notes.txt": "the user's own notes"}
    assert lines == [f"removed the replaced result's {COMPLETE}, ground_truth.ply, job.json, job.log, report.html "
                     "(this run wrote none)"]


def test_a_jobs_scratch_folder_holds_no_previous_result(tmp_path):
    """A job writes job.json and ground_truth.ply into its scratch folder before the reconstruction adds its result
    there: they are the coming result's files, not a previous one's to set aside (the reconstruction would not find
    its ground truth)."""
    scratch = tmp_path / ".tmp-cap-fast-0123456789abcdef"
    scratch.mkdir()
    for name in ("job.json", "ground_truth.ply"):
        (scratch / name).write_text(JOB_OWN[name])
    assert previous_result(scratch) == set()
    with replacing_result(scratch) as previous:
        assert previous == set() and (scratch / "ground_truth.ply").is_file()


def test_an_overwrite_that_fails_puts_the_job_result_back_whole(tmp_path):
    before = _job_result(tmp_path / "out")
    with pytest.raises(KeyboardInterrupt), replacing_result(tmp_path / "out"):
        (tmp_path / "out" / "mesh.ply").write_text("half of a new mesh")
        raise KeyboardInterrupt
    assert _files(tmp_path / "out") == before
    assert not (tmp_path / "out" / ASIDE_DIR).exists()


def test_reconstruct_overwrite_over_a_job_result_leaves_none_of_the_jobs_files(capture_and_gt, tmp_path, capsys):
    cap, _ = capture_and_gt
    out = tmp_path / "cap" / "recon" / "cap-fast"
    _job_result(out)
    assert _recon(cap, out, "--overwrite", "--no-gt") == 0
    left = _files(out)
    assert not set(JOB_OWN) & set(left), sorted(left)
    assert left["notes.txt"] == "the user's own notes"
    assert json.loads(left["report.json"])["steps"] == 1
    assert "removed the replaced result's .complete, ground_truth.ply, job.json, job.log" in capsys.readouterr().err


def test_a_ground_truth_from_the_result_being_replaced_is_refused_naming_it(capture_and_gt, tmp_path, capsys):
    """--overwrite sets the job's ground_truth.ply aside before the run reads its ground truth: passing it as --gt
    is refused in one line, the folder left as it was."""
    cap, _ = capture_and_gt
    out = tmp_path / "cap" / "recon" / "cap-fast"
    before = _job_result(out)
    assert _recon(cap, out, "--overwrite", "--gt", str(out / "ground_truth.ply")) == 1
    (line,) = _error_lines(capsys)
    assert f"--gt {out / 'ground_truth.ply'} is a file of the result in --out {out}" in line, line
    assert _files(out) == before
    check_ground_truth_kept(tmp_path / "elsewhere.ply", out)  # a file elsewhere, or a built-in scene, passes
    check_ground_truth_kept("builtin:bunny", out)
    with pytest.raises(ConfigError):
        check_ground_truth_kept(out / "mesh.ply", out)
