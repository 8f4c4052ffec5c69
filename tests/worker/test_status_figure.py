"""`spadscan worker --status` gives a done job's figure beside its result, as its log line does."""

from __future__ import annotations

import json

from spadscan.worker.queue import JobStatus
from spadscan.worker.status_detail import result_health, status_parts


def done_row(tmp_path, report: dict) -> JobStatus:
    result = tmp_path / "recon" / "scan-fast"
    result.mkdir(parents=True)
    (result / "report.json").write_text(json.dumps(report))
    return JobStatus(id="scan-fast", scan="scan", preset="fast", state="done", attempts=1, error=None,
                     result=str(result), holder=None, heartbeat_age_s=None)


def test_a_done_jobs_chamfer_is_in_its_status_line_and_its_json(tmp_path):
    row = done_row(tmp_path, {"chamfer_mm": 1.8222, "converged": True, "warnings": []})
    detail, warnings, _ = status_parts(row)
    assert detail.endswith("scan-fast (Chamfer to the ground truth 1.82 mm)") and warnings == []
    assert result_health(row)["chamfer_mm"] == 1.8222


def test_a_result_without_a_ground_truth_says_no_figure(tmp_path):
    row = done_row(tmp_path, {"chamfer_mm": None, "converged": False, "warnings": ["w"]})
    detail, warnings, _ = status_parts(row)
    assert "Chamfer" not in detail and detail.endswith("(not converged)") and warnings == ["w"]
    assert result_health(row)["chamfer_mm"] is None
