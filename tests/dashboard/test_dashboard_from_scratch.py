"""A live job whose scan was complete before a live fit began reconstructs it from scratch (worker/live/job.py): its
result holds no live record, and the dashboard labels it as what it is, never as the live reconstruction's result."""

from __future__ import annotations

import json

from dashboard_helpers import add_final_recon, complete_scan, serving, status
from page_helpers import browser_page
from spadscan.dashboard.server import address

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine
NOTE = "the scan completed with 2 views before the live fit started: reconstructing it from scratch"


def done_live_job(scan, report: dict) -> None:
    """Scan `scan`'s live job done, its result `<scan>-fast` with `report` (the live status as the worker leaves
    it)."""
    complete_scan(scan, 2)
    add_final_recon(scan, f"{scan.name}-fast")
    (scan / "recon" / f"{scan.name}-fast" / "report.json").write_text(json.dumps(report))
    (scan / "recon" / "live").mkdir()
    (scan / "recon" / "live" / "status.json").write_text(json.dumps(
        {"views_used": 2, "views_published": 2, "steps": 300, "state": "done", "job": f"{scan.name}-fast",
         "note": NOTE, "result": str(scan / "recon" / f"{scan.name}-fast"), "chamfer_mm": 4.0}))


def test_a_result_reconstructed_from_scratch_is_not_called_the_live_reconstructions(tmp_path):
    done_live_job(tmp_path / "scratch", {"preset": "fast", "chamfer_mm": 4.0})
    done_live_job(tmp_path / "followed", {"preset": "fast", "chamfer_mm": 2.0,
                                          "live": {"views_used": 40, "steps": 900, "final_start": "live"}})
    with serving(tmp_path) as server:
        recons = {s["name"]: s["recons"][0] for s in status(server)["scans"]}
        assert recons["scratch"]["from_live"] is True and recons["scratch"]["from_scratch"] is True
        assert recons["followed"]["from_live"] is True and "from_scratch" not in recons["followed"]
        with browser_page() as (page, seen):
            page.goto(address(server))
            pick = page.locator('#scans tr[data-scan="scratch"] a.pick')
            pick.wait_for(timeout=WAIT_MS)
            assert pick.text_content() == ("fast, Chamfer to the ground truth 4.00 mm (reconstructed from scratch: "
                                           "the scan was complete when the live job started (or was retried))")
            assert page.locator('#scans tr[data-scan="followed"] a.pick').text_content() == (
                "fast, Chamfer to the ground truth 2.00 mm (the live reconstruction's result: its final run continued "
                "from the live fit)")
            assert "live reconstruction's result" not in pick.text_content()
    assert not seen.errors, seen.errors
