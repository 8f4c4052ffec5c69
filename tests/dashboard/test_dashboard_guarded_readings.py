"""Readings of the root's files that the server must not get wrong, asked through /api/status as the page asks: a
result moved aside by a redo is no result of the scan's; a live job's result whose report cannot be read is not said
to be reconstructed from scratch; a scan's progress never reads over whole; a live status written just before its
job's running claim began is the earlier attempt's."""

from __future__ import annotations

import datetime as _dt
import json

from dashboard_helpers import add_final_recon, complete_scan, serving, status
from spadscan.worker.jobs import Job
from spadscan.worker.queue import Queue


def scan_answer(server, name: str) -> dict:
    return next(s for s in status(server)["scans"] if s["name"] == name)


def test_a_result_moved_aside_by_a_redo_is_not_listed(tmp_path):
    # `--redo` renames the earlier result to `<job>.replaced-<time>-<hex>` beside the new one (worker/jobs.py): it is
    # kept for the operator, never shown as one more of the scan's results
    complete_scan(tmp_path / "mug", 1)
    add_final_recon(tmp_path / "mug", "mug-fast.replaced-20261207T080000Z-ab12")
    add_final_recon(tmp_path / "mug", "mug-fast")
    with serving(tmp_path) as server:
        assert [r["id"] for r in scan_answer(server, "mug")["recons"]] == ["mug-fast"]


def test_a_live_result_whose_report_cannot_be_read_is_not_said_to_be_from_scratch(tmp_path):
    # "from scratch" is what a readable report without a live record says; an unreadable one says nothing of it
    for name, report in (("mug", '{"tok'), ("bowl", json.dumps({"preset": "fast", "chamfer_mm": 1.0}))):
        complete_scan(tmp_path / name, 1)
        add_final_recon(tmp_path / name, f"{name}-fast")
        result = tmp_path / name / "recon" / f"{name}-fast"
        (result / "report.json").write_text(report)
        live = tmp_path / name / "recon" / "live"
        live.mkdir()
        (live / "status.json").write_text(json.dumps({"state": "done", "views_used": 0, "job": f"{name}-fast",
                                                      "result": str(result)}))
    with serving(tmp_path) as server:
        mug = scan_answer(server, "mug")["recons"][0]
        assert mug["id"] == "mug-fast" and mug["from_live"] is True and mug["error"], mug
        assert "from_scratch" not in mug, mug
        bowl = scan_answer(server, "bowl")["recons"][0]
        assert bowl["id"] == "bowl-fast" and bowl.get("from_scratch") is True, bowl


def test_a_scan_with_more_poses_than_planned_reads_as_whole_not_over(tmp_path):
    # the page draws the progress as a bar's width: over 1 it would spill out of its cell
    complete_scan(tmp_path / "mug", 3)
    manifest = json.loads((tmp_path / "mug" / "scan.json").read_text())
    (tmp_path / "mug" / "scan.json").write_text(json.dumps({**manifest, "planned_poses": 2}))
    with serving(tmp_path) as server:
        mug = scan_answer(server, "mug")
        assert (mug["poses"], mug["planned"], mug["progress"]) == (3, 2, 1.0), mug


def test_a_live_status_written_just_before_its_jobs_claim_began_is_the_earlier_attempts(tmp_path):
    complete_scan(tmp_path / "vase", 1)
    queue = Queue.for_root(tmp_path)
    queue.enqueue(Job(id="vase-fast", scan="vase", live=True))
    assert queue.claim() is not None
    (record,) = queue.records("vase-fast")
    written = _dt.datetime.fromtimestamp(record["started_unix"] - 0.5, _dt.timezone.utc)
    live = tmp_path / "vase" / "recon" / "live"
    live.mkdir(parents=True)
    (live / "status.json").write_text(json.dumps({"state": "live", "views_used": 33, "steps": 136,
                                                  "job": "vase-fast", "updated_utc": written.isoformat()}))
    with serving(tmp_path) as server:
        (entry,) = scan_answer(server, "vase")["recons"]
        assert entry.get("earlier_attempt") is True, entry
        # half a second later, after the claim began: the running attempt's own
        (live / "status.json").write_text(json.dumps({"state": "live", "views_used": 34, "steps": 140,
                                                      "job": "vase-fast",
                                                      "updated_utc": (written + _dt.timedelta(seconds=1)).isoformat()}))
        (entry,) = scan_answer(server, "vase")["recons"]
        assert "earlier_attempt" not in entry and entry["summary"]["views_used"] == 34, entry
