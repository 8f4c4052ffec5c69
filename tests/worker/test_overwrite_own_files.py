"""`spadscan reconstruct --overwrite` over a folder that is not a worker job's result: a ground_truth.ply or job.log
the user keeps beside a plain `spadscan reconstruct` result (which writes neither) is the user's, and stays."""

from __future__ import annotations

import json

import pytest

from spadscan.worker import outputs
from spadscan.worker.outputs import previous_result, replacing_result

from test_reconstruct_cli import _recon, capture_and_gt  # noqa: F401 (a fixture)

pytestmark = pytest.mark.usefixtures("one_thread")

USERS = {"ground_truth.ply": "the user's own ground truth", "job.log": "the user's own notes"}


def _plain_result(out):
    out.mkdir(parents=True)
    (out / "mesh.ply").write_text("a mesh")
    (out / "report.json").write_text(json.dumps({"files": ["mesh.ply", "report.json"]}))
    for name, text in USERS.items():
        (out / name).write_text(text)


def test_the_users_files_beside_a_plain_result_are_no_part_of_it(tmp_path):
    out = tmp_path / "myrun"
    _plain_result(out)
    assert previous_result(out) == {"mesh.ply", "report.json"}
    with replacing_result(out):
        (out / "mesh.ply").write_text("the new mesh")
        (out / "report.json").write_text("{}")
    assert {name: (out / name).read_text() for name in USERS} == USERS


@pytest.mark.parametrize("marker", [(".complete", {"job": "cap-fast", "token": "0" * 16}),
                                    ("job.json", {"id": "cap-fast", "scan": "cap"})])
def test_a_folder_is_a_jobs_result_by_its_marker_or_its_job_file(tmp_path, marker):
    out = tmp_path / "cap-fast"
    _plain_result(out)
    (out / marker[0]).write_text(json.dumps(marker[1]))
    assert outputs.is_job_result(out)
    assert previous_result(out) == {"mesh.ply", "report.json", marker[0], *USERS}


def test_reconstruct_overwrite_keeps_the_users_ground_truth_and_log(capture_and_gt, tmp_path, capsys):
    cap, _ = capture_and_gt
    out = tmp_path / "myrun"
    assert _recon(cap, out, "--no-gt") == 0
    for name, text in USERS.items():
        (out / name).write_text(text)
    assert _recon(cap, out, "--overwrite", "--no-gt") == 0
    assert {name: (out / name).read_text() for name in USERS} == USERS
    assert "removed the replaced result's" not in capsys.readouterr().err
