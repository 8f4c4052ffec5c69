"""A result whose 3D view could not be written (a full disk) says so where an operator looks: its report.json's
warnings (and the page's), the worker's done line and `spadscan worker --status`, not only a line in job.log."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest
import trimesh

import spadscan.worker.report.folder_view as folder_view
from spadscan.cli import main as cli_main
from spadscan.worker.pool import Worker
from spadscan.worker.report.folder_view import ensure_view3d
from spadscan.worker.report.report_html import REPORT_HTML, write_report_html
from spadscan.worker.report.report_json import write_report
from spadscan.worker.report.view3d import VIEW3D
from spadscan.worker.worker_config import WorkerConfig

from test_watcher import make_scan

RECON = "test_missing_view_said:no_room_for_the_view_recon"
SAID = "no 3D view: view3d.html could not be written (No space left on device)"


def job_said(root: Path, job: str) -> str:
    """SAID, as a worker job's result says it: with the command that queues the job again, and what then runs it."""
    return (f"{SAID}; make room on its disk, then `spadscan worker --root {root.resolve()} --redo {job}` "
            f"queues the job again, this result moved aside, and a worker on that root and queue (a running one, or "
            f"one started with --once) reconstructs it with its view")


def _full_disk(folder, *args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device", str(Path(folder) / VIEW3D))


def no_room_for_the_view_recon(capture, out, *, preset="fast", budget_s=None, steps=None, gt=None, device="auto",
                               seed=0, started=None):
    """A stand-in reconstruction that finishes its result as reconstruct.py does (mesh, 3D view, report.json) on a
    disk where the 1 MB view does not fit."""
    folder_view.write_view3d = _full_disk
    out = Path(out)
    trimesh.creation.icosphere(subdivisions=1, radius=0.05).export(out / "mesh.ply")
    report = {"preset": preset, "capture": str(capture), "converged": True, "warnings": []}
    ensure_view3d(report, out)
    report["files"] = sorted(p.name for p in out.iterdir())
    write_report(out, report)
    write_report_html(report, out)
    return report


def test_a_view_that_cannot_be_written_is_one_of_the_reports_warnings(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(folder_view, "write_view3d", _full_disk)
    trimesh.creation.icosphere(subdivisions=1, radius=0.05).export(tmp_path / "mesh.ply")
    report = {"preset": "fast", "warnings": ["the run stopped on its budget"]}
    assert ensure_view3d(report, tmp_path) is None
    assert report["warnings"] == ["the run stopped on its budget", SAID]
    write_report_html(report, tmp_path)  # tries the view again: the warning is not said twice
    assert report["warnings"] == ["the run stopped on its budget", SAID]
    page = (tmp_path / REPORT_HTML).read_text()
    assert f"<strong>Warning:</strong> {SAID}" in page
    assert "spadscan: warning: no view3d.html in" in capsys.readouterr().err  # the job's log still has the details


@pytest.mark.usefixtures("recon_stand_ins")
def test_a_done_job_without_its_view_says_so_in_its_done_line_and_status(tmp_path, arun, capsys):
    root = tmp_path / "captures"
    root.mkdir()
    make_scan(root, "mug")
    lines: list[str] = []
    worker = Worker(WorkerConfig(root=root, once=True, poll_s=0.05, recon=RECON), log=lines.append)
    assert arun(worker.run()) == {"mug-fast": "done"}
    said = job_said(root, "mug-fast")
    result = root / "mug" / "recon" / "mug-fast"
    assert not (result / VIEW3D).exists()
    assert json.loads((result / "report.json").read_text())["warnings"] == [said]
    done = [line for line in lines if line.startswith("mug-fast done in ")]
    assert done and done[0].splitlines() == [done[0].splitlines()[0], f"  warning: {said}"], lines
    assert done[0].splitlines()[0].endswith(f" -> {result}"), "the done line itself stays short"
    assert cli_main(["worker", "--root", str(root), "--status", "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["state"] == "done" and row["warnings"] == [said], row
    assert cli_main(["worker", "--root", str(root), "--status"]) == 0
    header, row, warning, counts, workers = capsys.readouterr().out.splitlines()
    assert row.startswith("mug-fast") and row.endswith(f"{result} (1 warning below)"), row
    assert warning == " " * header.index("RESULT") + f"warning: {said}", "on its own line, under the result"
    assert os.path.isfile(result / "job.log")
